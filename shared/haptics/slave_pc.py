"""TDPA's slave port for a mapping that sends the slave position targets (docs/haptics.md).

The master's energy into the network, ``E_in_m`` (``measured_cp.energy_in_j``, master units),
reaches the slave side late; the slave port's observer counts the energy the slave has taken out
of the network by pushing against the tissue's force ``f_e`` along its commanded motion,
``E_out_s = ∫ max(−g f_e·v_s, 0) dt`` with ``g = force_scale / position_scale`` (slave power in
master units). When ``W_s = ΔE_in_m − ΔE_out_s`` (both counted from the engage) would fall below
zero, the controller changes this period's motion by ``β f_e`` with ``β = −W_s / (dt g |f_e|²)``
(backing the instrument off along the force just enough to dissipate the deficit; a step is capped
at ``max_correction_m``); with energy to spare it walks the accumulated offset (the drift) back
over ``drift_time_s``, spending at most half of the spare. The step is
:func:`telesurg.shared.haptics.tdpa.slave_pc_step`, the bench's ``Tdpa`` slave side, applied to
absolute targets.

Example::

    pc = SlavePassivity(force_scale=0.5)
    pc.engage(e_in_m=pose.energy_in_j)
    pc.force = f_e                                   # each measured_cf (base frame, N)
    target = pc.step(target, pose.energy_in_j, position_scale, dt)
"""

from __future__ import annotations

import numpy as np
from telesurg.shared.haptics.tdpa import slave_pc_step


class SlavePassivity:
    """The slave port's passivity observer and controller (module doc)."""

    def __init__(
        self, force_scale: float, max_correction_m: float = 0.0005, drift_time_s: float = 1.0
    ) -> None:
        self.force_scale = force_scale
        self.max_correction_m = max_correction_m
        self.drift_time_s = drift_time_s
        self.force = np.zeros(3)  # N, the newest contact force on the instrument (base frame)
        self.offset = np.zeros(3)  # m: what the controller has moved the target by (the drift)
        self.e_out = 0.0  # J (master units) out of the network at the slave port since the engage
        self.e_in0 = 0.0  # the master's E_in_m at the engage
        self.x_prev: np.ndarray | None = None
        self.w_min = 0.0  # J: the lowest observed W_s after the controller acted
        self.dissipated = 0.0  # J: what the controller removed
        self.offset_max = 0.0  # m: the largest drift
        self.prev_ns = 0  # the stamp of the master sample the last step was for (its dt)

    def report(self) -> str:
        """What the controller saw and did, for the service's log at exit."""
        return (
            f"slave passivity: observed W_s min {self.w_min * 1e3:.3f} mJ, dissipated "
            f"{self.dissipated * 1e3:.3f} mJ, drift max {self.offset_max * 1e3:.2f} mm"
        )

    def engage_at(self, e_in_m: float, stamp_ns: int) -> None:
        """:meth:`engage` at the master sample stamped ``stamp_ns`` (the next :meth:`follow`'s dt
        counts from it)."""
        self.engage(e_in_m)
        self.prev_ns = stamp_ns

    def follow(self, target: np.ndarray, e_in_m: float, stamp_ns: int, position_scale: float) -> np.ndarray:
        """:meth:`step` for the master sample stamped ``stamp_ns``, its dt the time since the
        previous sample's stamp."""
        dt, self.prev_ns = (stamp_ns - self.prev_ns) / 1e9, stamp_ns
        return self.step(target, e_in_m, position_scale, dt)

    def engage(self, e_in_m: float) -> None:
        """A new engagement: count from here, no offset."""
        self.e_in0, self.e_out = e_in_m, 0.0
        self.offset[:] = 0.0
        self.x_prev = None

    def step(self, target: np.ndarray, e_in_m: float, position_scale: float, dt: float) -> np.ndarray:
        """The target (m, base frame) after the controller, for this period of ``dt`` s."""
        x = np.asarray(target, dtype=float) + self.offset
        if self.x_prev is None or dt <= 0.0:
            self.x_prev = x
            return x
        g = self.force_scale / max(position_scale, 1e-6)
        f = self.force
        v = (x - self.x_prev) / dt
        e_in = e_in_m - self.e_in0
        w = e_in - (self.e_out + max(-g * float(f @ v), 0.0) * dt)
        dv, removed = slave_pc_step(f, w, self.offset, g, dt, self.max_correction_m, self.drift_time_s)
        v = v + dv
        self.offset += dv * dt
        self.dissipated += removed
        self.e_out += max(-g * float(f @ v), 0.0) * dt
        self.w_min = min(self.w_min, e_in - self.e_out)
        self.offset_max = max(self.offset_max, float(np.linalg.norm(self.offset)))
        out: np.ndarray = self.x_prev + v * dt
        self.x_prev = out
        return out
