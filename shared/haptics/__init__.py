"""Bilateral force feedback: the pure parts (numpy in, numpy out; no I/O, no bus).

* :mod:`.tdpa` — the time-domain passivity approach for position-forward / force-back
  teleoperation (passivity observers at both ports, passivity controllers), the naive loop and
  wave variables, behind one :class:`~.tdpa.Bilateral` seam chosen by name (``none``, ``naive``,
  ``tdpa``, ``wave``).
* :mod:`.render` — what a haptic loop does to a force before a device gets it: the device's force
  limit, a rate limit on changes, a fade to zero when the force stream is stale or the watchdog
  holds (never a step), and a check of every incoming force (finite, within range).

Units: m, m/s, N, J, s; vectors are (3,) arrays in the master frame (the slave's ``base`` frame
rotated into the master's by the mapping; the bench uses the identity). docs/haptics.md gives the
equations as implemented.
"""

from __future__ import annotations

from telesurg.shared.haptics.render import ForceRenderer, RenderConfig, check_force
from telesurg.shared.haptics.tdpa import (
    CONTROLLERS,
    Bilateral,
    BilateralConfig,
    MasterPacket,
    SlavePacket,
    SlavePortWork,
    make_bilateral,
)

__all__ = [
    "CONTROLLERS",
    "Bilateral",
    "BilateralConfig",
    "ForceRenderer",
    "MasterPacket",
    "RenderConfig",
    "SlavePacket",
    "SlavePortWork",
    "check_force",
    "make_bilateral",
]
