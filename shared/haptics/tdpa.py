"""Position forward, force back: four bilateral controllers behind one seam.

Each side runs one :class:`Bilateral` (the same object type on both sides; the master side calls
:meth:`Bilateral.master_step`, the slave side :meth:`Bilateral.slave_step`). They exchange one
:class:`MasterPacket` per master period and one :class:`SlavePacket` per slave force period over a
channel that may delay, reorder and lose them: a packet older than the newest one taken is
ignored, and without a new packet a side keeps the last values (zero-order hold).

Sign conventions (docs/haptics.md, "Energy"): ``x_m``, ``v_m`` are the master's displacement from
its anchor and its velocity; ``F_m`` the force the device applies to the hand; ``f_e`` the force
the environment (tissue) applies to the instrument; ``x_s``, ``v_s`` the slave's commanded
displacement from its anchor and its rate. Power flowing *into* the network (the 2-port between the
hand and the tissue: the channel, both scales, both controllers) at the master port is
``p_m = -F_m·v_m``; power flowing *out* of it at the slave port is ``p_s = -g f_e·v_s`` with
``g = force_scale / position_scale`` (slave power in master units: lossless scaled transmission
then conserves energy). Each port keeps its monotone sums::

    E_in_m  = Σ max(p_m, 0) dt      E_out_m = Σ max(-p_m, 0) dt
    E_out_s = Σ max(p_s, 0) dt      E_in_s  = Σ max(-p_s, 0) dt

and sends its ``E_in`` with every packet. The passivity observers (Ryu, Artigas, Preusche 2010):

    W_s(k) = E_in_m(k - D_f) - E_out_s(k)        (slave side, with the newest master packet)
    W_m(k) = E_in_s(k - D_b) - E_out_m(k)        (master side, with the newest slave packet)

The network is passive while both are ≥ 0. ``tdpa`` adds the passivity controllers, which
dissipate exactly the deficit and nothing when there is none:

* slave (velocity output, series PC): ``v_s = v_sd + β f_e``, ``β = -W_s / (dt g |f_e|²)`` when
  the tentative ``W_s < 0`` (it backs the instrument off along the contact force);
* master (force output, parallel PC): ``F_m = F_md - α v_m``, ``α = -W_m / (dt |v_m|²)``,
  applied to the force the haptic loop shaped (after its rate limit: a damper opposing the hand's
  motion, dissipative by construction; the device's force limit still bounds it);

and a drift compensator that pulls ``x_s`` back to ``position_scale · x_m`` only with the energy
the slave observer has to spare (never more than half of ``W_s`` per period).
``naive`` sends the same quantities with no controller; ``wave`` transmits wave variables
(Niemeyer & Slotine 1991) ``u = (F + b ẋ)/√(2b)`` forward and ``v = (F − b ẋ)/√(2b)`` back, which
is passive for any constant delay; ``none`` is position forward without force feedback. Every
controller runs the observers, so the bench reports the port energies of all four.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from telesurg.shared.errors import ConfigError

#: the controllers, by name (the bench's and the config's ``controller`` values)
CONTROLLERS = ("none", "naive", "tdpa", "wave")
_EPS_F = 1e-3  # N: below this contact force the slave PC has nothing to act through
_EPS_V = 1e-4  # m/s: below this master speed the master PC has nothing to act through

Vec = np.ndarray


@dataclass(frozen=True)
class BilateralConfig:
    """The bilateral controller's settings (``[haptics]``)."""

    controller: str = "tdpa"  # one of CONTROLLERS
    position_scale: float = 1.0  # slave displacement per master displacement (1: same size)
    force_scale: float = 0.5  # master force per slave contact force (0.5: half, within a Touch's 3.3 N)
    wave_impedance: float = 30.0  # N·s/m: the wave variables' b (wave only)
    max_correction_m: float = 0.0005  # m per period: largest slave PC / drift correction step
    drift_time_s: float = 0.2  # s: time constant of the drift compensator (tdpa)

    def __post_init__(self) -> None:
        if self.controller not in CONTROLLERS:
            raise ConfigError(
                f"haptics controller {self.controller!r} unknown; valid: {', '.join(CONTROLLERS)}"
            )
        for name in ("position_scale", "force_scale", "wave_impedance", "max_correction_m", "drift_time_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"haptics {name} = {value!r}: must be a finite number > 0")


@dataclass(frozen=True)
class MasterPacket:
    """Master → slave, once per master period."""

    seq: int  # 1, 2, ...: newer is larger
    position: Vec  # m, (3,): x_m (wave: unused)
    energy_in: float  # J: E_in_m so far
    wave: Vec = field(default_factory=lambda: np.zeros(3))  # √W: wave variable u_m (wave only)


@dataclass(frozen=True)
class SlavePacket:
    """Slave → master, once per slave force period."""

    seq: int
    force: Vec  # N, (3,): f_e, what the tissue exerts on the instrument
    energy_in: float  # J (master units): E_in_s so far
    wave: Vec = field(default_factory=lambda: np.zeros(3))  # √W: wave variable v_s (wave only)


@dataclass
class PortEnergy:
    """The monotone energy sums of one port, J."""

    e_in: float = 0.0
    e_out: float = 0.0

    def add(self, p_in: float, dt: float) -> None:
        """Add one period of power flowing into the network (W; negative: out of it)."""
        if p_in > 0:
            self.e_in += p_in * dt
        else:
            self.e_out -= p_in * dt


class SlavePortWork:
    """``E_in_s`` of a slave that measures the environment's force, in slave units (J): the work
    the environment has done on the instrument along its motion, summed over the samples where it
    is positive (the tissue pushing the instrument back). A master turns it into master units with
    ``force_scale / position_scale``."""

    def __init__(self) -> None:
        self.e_in = 0.0
        self._x: Vec | None = None

    def add(self, f_e: Vec, x_s: Vec) -> float:
        """Take the force ``f_e`` (N) measured with the instrument at ``x_s`` (m); returns E_in."""
        x = np.array(x_s, dtype=float)
        if self._x is not None:
            work = float(np.dot(np.asarray(f_e, dtype=float), x - self._x))
            if work > 0.0:
                self.e_in += work
        self._x = x
        return self.e_in


def slave_pc_step(
    f_e: Vec, w: float, drift: Vec, g: float, dt: float, max_correction_m: float, drift_time_s: float
) -> tuple[Vec, float]:
    """The slave passivity controller's change of this period's slave velocity (m/s), and the
    out-energy it removed (J, master units): with the observed ``W_s`` = ``w`` below zero and a
    force to act through, ``β f_e`` with ``β = −W_s / (dt g |f_e|²)`` (backing off along the force
    just enough); else the drift compensator, ``−drift / drift_time_s`` when that spends at most
    half of the spare energy. Each step capped at ``max_correction_m`` per period."""
    cap = max_correction_m / dt
    ff = float(f_e @ f_e)
    if w < 0 and ff > _EPS_F**2:
        dv = (-w / (dt * g * ff)) * f_e
        n = float(np.linalg.norm(dv))
        if n > cap:
            dv *= cap / n
        return dv, g * float(f_e @ dv) * dt
    dv = -drift / drift_time_s
    n = float(np.linalg.norm(dv))
    if n > cap:
        dv *= cap / n
    extra = -g * float(f_e @ dv) * dt  # extra energy out of the network
    return (dv, 0.0) if extra <= 0.5 * max(w, 0.0) else (np.zeros(3), 0.0)


class Bilateral:
    """Position forward / force back without a controller on the energy (``naive``); the
    subclasses change what each side computes. One instance per side (or one for both in a
    simulation: the two sides share no state)."""

    name = "naive"
    feedback = True  # False: the master displays no force (``none``)

    def __init__(self, cfg: BilateralConfig) -> None:
        self.cfg = cfg
        self.g = cfg.force_scale / cfg.position_scale
        # master side
        self.master = PortEnergy()
        self._m_seq = 0
        self._m_rx = 0  # newest slave packet taken
        self.f_rx = np.zeros(3)  # N: newest f_e from the slave
        self.e_in_s_rx = 0.0  # J: newest E_in_s
        self.w_rx = np.zeros(3)  # wave v from the slave
        self.dissipated_m = 0.0  # J: dissipated by the master PC
        # slave side
        self.slave = PortEnergy()
        self._s_seq = 0
        self._s_rx = 0
        self.x_rx = np.zeros(3)  # m: newest x_m
        self.e_in_m_rx = 0.0
        self.u_rx = np.zeros(3)  # wave u from the master
        self.x_sd = np.zeros(3)  # m: slave target from the newest packet, position_scale · x_m
        self.x_s = np.zeros(3)  # m: slave command (displacement from its anchor)
        self.dissipated_s = 0.0

    # -- observers -----------------------------------------------------------------------------
    @property
    def observed_master(self) -> float:
        """W_m, J: the master side's passivity observer."""
        return self.e_in_s_rx - self.master.e_out

    @property
    def observed_slave(self) -> float:
        """W_s, J: the slave side's passivity observer."""
        return self.e_in_m_rx - self.slave.e_out

    @property
    def drift(self) -> Vec:
        """m, (3,): slave command − position_scale · newest master position."""
        return self.x_s - self.x_sd

    # -- master side ---------------------------------------------------------------------------
    def take_slave(self, rx: SlavePacket | None) -> None:
        if rx is not None and rx.seq > self._m_rx:
            self._m_rx = rx.seq
            self.f_rx = np.asarray(rx.force, dtype=float)
            self.e_in_s_rx = float(rx.energy_in)
            self.w_rx = np.asarray(rx.wave, dtype=float)

    def master_force(self, x_m: Vec, v_m: Vec, dt: float) -> Vec:
        """The force to display (N) before the master PC."""
        return self.cfg.force_scale * self.f_rx if self.feedback else np.zeros(3)

    def master_step(self, x_m: Vec, v_m: Vec, rx: SlavePacket | None, dt: float) -> Vec:
        """One master period: take the newest slave packet, return the force for the hand (N)
        before the passivity controller. The haptic loop shapes it (limit, rate, fade), then
        calls :meth:`master_passivity` and :meth:`master_sent` with the force it displays."""
        self.take_slave(rx)
        return self.master_force(x_m, v_m, dt)

    def master_passivity(self, force: Vec, v_m: Vec, dt: float) -> Vec:
        """The master passivity controller on the shaped force (N); none here."""
        return force

    def master_sent(self, force: Vec, x_m: Vec, v_m: Vec, dt: float) -> MasterPacket:
        """Account the displayed force's power at the master port; the packet to send."""
        self.master.add(-float(force @ v_m), dt)
        self._m_seq += 1
        return MasterPacket(
            self._m_seq, np.array(x_m, dtype=float), self.master.e_in, self._wave_out(force, v_m)
        )

    def _wave_out(self, force: Vec, v_m: Vec) -> Vec:
        return np.zeros(3)

    # -- slave side ----------------------------------------------------------------------------
    def take_master(self, rx: MasterPacket | None) -> bool:
        if rx is not None and rx.seq > self._s_rx:
            self._s_rx = rx.seq
            self.x_rx = np.asarray(rx.position, dtype=float)
            self.e_in_m_rx = float(rx.energy_in)
            self.u_rx = np.asarray(rx.wave, dtype=float)
            return True
        return False

    def slave_velocity(self, f_e: Vec, dt: float) -> Vec:
        """The slave's commanded velocity (m/s) this period."""
        x_sd = self.cfg.position_scale * self.x_rx
        v = (x_sd - self.x_sd) / dt
        self.x_sd = x_sd
        return v

    def slave_step(self, rx: MasterPacket | None, f_e: Vec, dt: float) -> Vec:
        """One slave period: the slave's commanded displacement from its anchor (m)."""
        self.take_master(rx)
        f_e = np.asarray(f_e, dtype=float)
        v = self.slave_velocity(f_e, dt)
        self.slave.add(self.g * float(f_e @ v), dt)  # into the network: -p_s = g f_e·v
        self.x_s = self.x_s + v * dt
        return self.x_s

    def slave_packet(self, f_e: Vec) -> SlavePacket:
        """The packet the slave sends (at its force rate)."""
        self._s_seq += 1
        return SlavePacket(self._s_seq, np.array(f_e, dtype=float), self.slave.e_in, self._wave_back(f_e))

    def _wave_back(self, f_e: Vec) -> Vec:
        return np.zeros(3)


class NoFeedback(Bilateral):
    """Position forward only: the master displays nothing."""

    name = "none"
    feedback = False


class Tdpa(Bilateral):
    """Position forward / force back with passivity controllers at both ports."""

    name = "tdpa"

    def master_passivity(self, force: Vec, v_m: Vec, dt: float) -> Vec:
        f = np.asarray(force, dtype=float)
        p = -float(f @ v_m)
        w = self.e_in_s_rx - (self.master.e_out + max(-p, 0.0) * dt)
        vv = float(v_m @ v_m)
        if w < 0 and vv > _EPS_V**2:
            alpha = -w / (dt * vv)
            f = f - alpha * v_m
            self.dissipated_m += -w
        return f

    def slave_velocity(self, f_e: Vec, dt: float) -> Vec:
        v = super().slave_velocity(f_e, dt)
        p = -self.g * float(f_e @ v)  # out of the network at the slave port
        w = self.e_in_m_rx - (self.slave.e_out + max(p, 0.0) * dt)
        drift = (self.x_s + v * dt) - self.x_sd
        dv, removed = slave_pc_step(
            f_e, w, drift, self.g, dt, self.cfg.max_correction_m, self.cfg.drift_time_s
        )
        self.dissipated_s += removed
        out: Vec = v + dv
        return out


class Wave(Bilateral):
    """Wave variables: passive for any constant delay, at the price of wave reflections and
    position drift."""

    name = "wave"

    def __init__(self, cfg: BilateralConfig) -> None:
        super().__init__(cfg)
        self.b = cfg.wave_impedance
        self.r = math.sqrt(2.0 * self.b)
        self._f_s = np.zeros(3)

    def master_force(self, x_m: Vec, v_m: Vec, dt: float) -> Vec:
        # F = b ẋ_m + √(2b) v (what the hand pushes into the network); the device applies −F
        return -(self.b * v_m + self.r * self.w_rx)

    def _wave_out(self, force: Vec, v_m: Vec) -> Vec:
        # u_m = (F + b ẋ_m)/√(2b) with the force actually displayed (F = −force)
        out: Vec = (-force + self.b * v_m) / self.r
        return out

    def slave_velocity(self, f_e: Vec, dt: float) -> Vec:
        self.x_sd = self.cfg.position_scale * self.x_rx
        self._f_s = -self.cfg.force_scale * f_e  # the force on the wave's slave port (master units)
        xdot = (self.r * self.u_rx - self._f_s) / self.b  # master units
        out: Vec = self.cfg.position_scale * xdot
        return out

    def _wave_back(self, f_e: Vec) -> Vec:
        f_s = -self.cfg.force_scale * np.asarray(f_e, dtype=float)
        out: Vec = math.sqrt(2.0 / self.b) * f_s - self.u_rx
        return out


_KINDS: dict[str, type[Bilateral]] = {"none": NoFeedback, "naive": Bilateral, "tdpa": Tdpa, "wave": Wave}


def make_bilateral(cfg: BilateralConfig) -> Bilateral:
    """The controller ``cfg.controller`` names."""
    return _KINDS[cfg.controller](cfg)
