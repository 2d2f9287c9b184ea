"""What a haptic loop does to a force before the device gets it.

:class:`ForceRenderer` runs once per haptic period (≥ 1 kHz) and returns the force to write:

1. **Check.** :func:`check_force` refuses a force that is not three finite numbers or whose
   magnitude exceeds ``max_input_n`` (a forged or corrupted message); a refused force is counted
   (``rejected``) and the renderer goes on from what it had — it never reaches the device.
2. **Fade.** While the force stream is stale (nothing accepted for ``stale_ms``) or the watchdog
   holds, the target is zero; the output then moves towards it at most ``fade_n_per_s`` — a fade,
   never a step.
3. **Rate limit.** Otherwise the output moves towards the target at most ``rate_n_per_s``.
4. **Limit.** The output's magnitude never exceeds the device's ``limit_n`` (its direction kept);
   ``clipped`` counts the periods it bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from telesurg.shared.errors import MessageError


@dataclass(frozen=True)
class RenderConfig:
    """A haptic loop's limits (``[haptics]``)."""

    limit_n: float = 3.3  # N: the device's force limit (Touch: 3.3 N peak, docs/haptics.md)
    rate_n_per_s: float = 200.0  # N/s: largest change of the output while the stream is fresh
    fade_n_per_s: float = 10.0  # N/s: fade to zero when stale or held (3.3 N → 0 in 0.33 s)
    stale_ms: float = 20.0  # ms: no accepted force for this long → fade (the slave sends at 500 Hz)
    max_input_n: float = 100.0  # N: a larger incoming force is refused as corrupt (not clipped)


def check_force(force: object, max_n: float) -> np.ndarray:
    """``force`` as a (3,) array of finite numbers with magnitude ≤ ``max_n``; MessageError if not."""
    try:
        f = np.asarray(force, dtype=float)
    except (TypeError, ValueError) as exc:
        raise MessageError(f"force {force!r}: not three numbers") from exc
    if f.shape != (3,):
        raise MessageError(f"force of shape {f.shape}: expected three numbers")
    if not np.all(np.isfinite(f)):
        raise MessageError(f"force {f.tolist()}: not finite")
    n = float(np.linalg.norm(f))
    if n > max_n:
        raise MessageError(f"force of {n:.3g} N above the {max_n:g} N any tissue can give")
    return f


class ForceRenderer:
    """Force shaping of one haptic device (see the module doc)."""

    def __init__(self, cfg: RenderConfig) -> None:
        for name in ("limit_n", "rate_n_per_s", "fade_n_per_s", "stale_ms", "max_input_n"):
            value = getattr(cfg, name)
            if not (math.isfinite(value) and value > 0):
                raise MessageError(f"haptics {name} = {value!r}: must be a finite number > 0")
        self.cfg = cfg
        self.target = np.zeros(3)  # N: the newest accepted force
        self.out = np.zeros(3)  # N: the last output
        self.fresh_at = -math.inf  # s: when the newest accepted force came
        self.rejected = 0
        self.clipped = 0
        self.fading = False

    def offer(self, force: object, now: float) -> bool:
        """A new force for the device (N, master frame) at ``now`` (s, monotonic); False (and
        counted) if it is refused."""
        try:
            f = check_force(force, self.cfg.max_input_n)
        except MessageError:
            self.rejected += 1
            return False
        self.target = f
        self.fresh_at = now
        return True

    def step(self, now: float, dt: float, hold: bool = False) -> np.ndarray:
        """The force to write this period (N, (3,))."""
        cfg = self.cfg
        self.fading = hold or (now - self.fresh_at) * 1e3 > cfg.stale_ms
        goal = np.zeros(3) if self.fading else self.target
        rate = cfg.fade_n_per_s if self.fading else cfg.rate_n_per_s
        step = goal - self.out
        n = float(np.linalg.norm(step))
        if n > rate * dt:
            step *= rate * dt / n
        out = self.out + step
        mag = float(np.linalg.norm(out))
        if mag > cfg.limit_n:
            out *= cfg.limit_n / mag
            self.clipped += 1
        self.out = out
        return out.copy()
