"""The ``scripted`` master device: a circle, a figure-eight or a CSV trajectory (m, master frame),
with a clutch-pedal schedule — for demos, tests and replaying a surgeon's path.

Example: ``telesurg master-capture --set device=scripted --set scripted.trajectory=figure8``.
"""

from __future__ import annotations

import csv
import logging
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType

import numpy as np
from telesurg.services.master_capture.devices import DeviceSample, MasterDevice, register
from telesurg.shared.errors import ConfigError

log = logging.getLogger(__name__)

TRAJECTORIES = ("circle", "figure8", "csv")


@dataclass
class ScriptedConfig:
    """Scripted master: a path in the master frame and a clutch-pedal schedule."""

    trajectory: str = "circle"  # circle | figure8 | csv
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)  # m, master frame: path centre
    radius: float = 0.04  # m: circle radius / figure-eight half-width
    period_s: float = 8.0  # s: one lap
    plane: str = "xy"  # plane of the circle / figure-eight: xy, xz or yz
    csv_path: str = ""  # CSV with columns t,x,y,z[,clutch] (s, m, 0/1); looped
    # [t_on, t_off] intervals (s since start) while the clutch pedal is pressed. The default
    # presses after 1 s, so a restarted master never engages in its first second.
    clutch: list[list[float]] = field(default_factory=lambda: [[1.0, 1e9]])
    clutch_repeat_s: float = 0.0  # s: if > 0, the clutch schedule repeats with this period
    operator_present: bool = True  # the operator-present sensor reads this constant
    # s: when the mapping refuses an engage of this master (its teleop state goes ENGAGING →
    # HOLDING) while the schedule says pressed, the pedal is released at once and pressed again
    # this long after, as an operator would (the press-again rule); 0 = off: the next press is the
    # schedule's (clutch_repeat_s later). In [0.1, 60] s when on.
    retry_refused_engage_s: float = 1.0

    def validate(self) -> None:
        """Raise ConfigError naming the valid options."""
        if self.trajectory not in TRAJECTORIES:
            raise ConfigError(
                f"scripted trajectory {self.trajectory!r} invalid; valid: {', '.join(TRAJECTORIES)}"
            )
        if self.plane not in ("xy", "xz", "yz"):
            raise ConfigError(f"scripted plane {self.plane!r} invalid; valid: xy, xz, yz")
        if self.clutch_repeat_s < 0:
            raise ConfigError("scripted clutch_repeat_s must be >= 0 (0: no repeat)")
        if self.period_s <= 0 or self.radius < 0:
            raise ConfigError("scripted period_s must be > 0 and radius >= 0")
        for iv in self.clutch:
            if len(iv) != 2 or iv[0] > iv[1]:
                raise ConfigError(f"clutch interval {iv} must be [t_on, t_off] with t_on <= t_off")
        if self.retry_refused_engage_s != 0 and not 0.1 <= self.retry_refused_engage_s <= 60.0:
            raise ConfigError(
                f"scripted retry_refused_engage_s={self.retry_refused_engage_s} outside [0.1, 60] s (0: off)"
            )
        if self.trajectory == "csv" and not self.csv_path:
            raise ConfigError("scripted trajectory 'csv' needs csv_path")


class EngageRetry:
    """The scripted pedal's answer to a refused engage: release, then press again ``retry_s`` later.

    :meth:`refused` is told of each refusal (from a bus thread; one refusal is one teleop-state
    entry, named by its ``since_ns``, however often the state is re-sent); :meth:`clutch` (the
    sampling loop) turns the schedule's pedal into the pedal sent. A refusal while the schedule has
    the pedal released is dropped: the schedule's own next press is a new one.
    """

    def __init__(self, retry_s: float) -> None:
        self.retry_s = retry_s
        self.retries = 0  # refusals answered by a release and a new press
        self._lock = threading.Lock()
        self._pending = False
        self._last_since: int | None = None
        self._release_until = -math.inf  # device time (s) the pedal is held released until

    def refused(self, since_ns: int) -> bool:
        """An engage was refused (its HOLDING entered at wall-clock ``since_ns``); True if new."""
        with self._lock:
            if since_ns == self._last_since:
                return False
            self._last_since, self._pending = since_ns, True
            return True

    def clutch(self, pressed: bool, t: float) -> bool:
        """The pedal at device time ``t`` s, given the schedule's ``pressed``."""
        with self._lock:
            pending, self._pending = self._pending, False
        if pending and pressed and t >= self._release_until:
            self._release_until = t + self.retry_s
            self.retries += 1
            log.info("scripted pedal released after a refused engage; pressing again in %.2f s", self.retry_s)
        return pressed and t >= self._release_until


@register
class ScriptedDevice(MasterDevice):
    """A master that plays a path; see :class:`ScriptedConfig`.

    With ``retry_refused_engage_s`` > 0 it has an :attr:`engage_retry`: master_capture tells it
    of the mapping's refusals (:meth:`EngageRetry.refused`) and the pedal presses again.
    """

    name = "scripted"
    config = ScriptedConfig
    table = "scripted"

    def __init__(self, cfg: ScriptedConfig) -> None:
        cfg.validate()
        self.cfg = cfg
        r = cfg.retry_refused_engage_s
        self.engage_retry: EngageRetry | None = EngageRetry(r) if r > 0 else None
        self._csv: np.ndarray | None = None
        axes = {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}[cfg.plane]
        self._u, self._v = axes

    def __enter__(self) -> ScriptedDevice:
        if self.cfg.trajectory == "csv":
            self._csv = _load_csv(Path(self.cfg.csv_path))
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._csv = None

    def read(self, t: float) -> DeviceSample:
        """Path position at ``t`` s; identity orientation."""
        c = self.cfg
        tc = t % c.clutch_repeat_s if c.clutch_repeat_s > 0 else t
        clutch = any(on <= tc < off for on, off in c.clutch)
        p = np.array(c.center, dtype=float)
        if c.trajectory == "csv":
            assert self._csv is not None, "device not opened"
            data = self._csv
            tt = t % data[-1, 0] if data[-1, 0] > 0 else 0.0
            for i in range(3):
                p[i] = float(np.interp(tt, data[:, 0], data[:, 1 + i]))
            if data.shape[1] > 4:
                clutch = clutch and bool(np.interp(tt, data[:, 0], data[:, 4]) >= 0.5)
        else:
            w = 2.0 * math.pi * t / c.period_s
            if c.trajectory == "circle":
                du, dv = c.radius * math.cos(w), c.radius * math.sin(w)
            else:  # figure8 (Gerono lemniscate)
                du, dv = c.radius * math.sin(w), c.radius * math.sin(w) * math.cos(w)
            p[self._u] += du
            p[self._v] += dv
        if self.engage_retry is not None:
            clutch = self.engage_retry.clutch(clutch, t)
        return DeviceSample(
            (float(p[0]), float(p[1]), float(p[2])),
            (0.0, 0.0, 0.0, 1.0),
            clutch,
            c.operator_present,
        )


def _load_csv(path: Path) -> np.ndarray:
    try:
        with path.open(newline="") as f:
            rows = [r for r in csv.reader(f) if r and not r[0].lstrip().startswith("#")]
    except FileNotFoundError:
        raise ConfigError(f"trajectory CSV {path} not found") from None
    if rows and not _is_number(rows[0][0]):
        rows = rows[1:]  # header
    try:
        data = np.array([[float(x) for x in r] for r in rows], dtype=float)
    except ValueError as exc:
        raise ConfigError(f"trajectory CSV {path}: {exc}") from None
    if data.ndim != 2 or data.shape[0] < 2 or data.shape[1] < 4:
        raise ConfigError(f"trajectory CSV {path} needs >= 2 rows of t,x,y,z[,clutch]")
    if not np.all(np.isfinite(data)) or np.any(np.diff(data[:, 0]) <= 0):
        raise ConfigError(f"trajectory CSV {path}: values must be finite and t increasing")
    return data


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True
