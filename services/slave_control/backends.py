"""Slave backends behind one interface: the MuJoCo simulation and a real arm's servo controller.

A backend is a context manager that owns the robot: ``command(q)`` sets joint position targets,
``step(n)`` advances it by ``n`` control periods, and ``read()`` returns the measured state.
A backend that can fail at run time (the ``serial`` one: link loss, controller fault, controller
timeout, shadow divergence) says so in ``SlaveReading.fault``; the arm cores then hold
(:class:`~telesurg.services.slave_control.arm.FaultHold`). mujoco is imported lazily inside the
MuJoCo backend. The serial backend (:mod:`telesurg.services.slave_control.serial_backend`) builds on
this module; :mod:`telesurg.services.slave_control.factory` picks one by its registered name (so
neither backend module imports the other's chooser: no import loop).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Protocol

import numpy as np
from telesurg.shared.errors import ConfigError
from telesurg.shared.robots.api import PUSH_POINTS


@dataclass(frozen=True)
class ShadowDivergence:
    """How far a real slave is from its MuJoCo shadow (fed the same setpoints).

    Attributes:
        max_rad: largest |predicted − measured| over the joints, rad (m for a prismatic joint).
        joint: name of the joint where it is largest.
        predicted: that joint's predicted position, rad / m.
        measured: that joint's measured position, rad / m.
        tip_m: largest distance between the predicted and the measured tip over the arms, m.
    """

    max_rad: float
    joint: str
    predicted: float
    measured: float
    tip_m: float

    def describe(self) -> str:
        """One line for events and hold causes."""
        return (
            f"{self.max_rad:.4f} rad at {self.joint} (predicted {self.predicted:+.4f}, "
            f"measured {self.measured:+.4f}), tip {self.tip_m * 1e3:.1f} mm"
        )


@dataclass(frozen=True)
class SlaveReading:
    """Measured slave state.

    Attributes:
        position: joint positions, rad, shape (n,).
        velocity: joint velocities, rad/s, shape (n,).
        effort: actuator torques, N·m, shape (n,).
        tip_position: forceps tip in the base frame, m, shape (3,).
        tip_quat: tip orientation, unit quaternion (x, y, z, w).
        sim_time: backend time, s.
        external_torque: estimated external joint torques (a push by hand, contact), N·m,
            shape (n,); zeros if the backend cannot estimate them.
    """

    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    tip_position: np.ndarray
    tip_quat: np.ndarray
    sim_time: float
    external_torque: np.ndarray | None = None
    site_positions: np.ndarray | None = None  # (k, 3) m: the backend's extra sites, in order
    # why the backend cannot be trusted to move now ("" = fine): link lost, controller fault,
    # controller watchdog, shadow divergence. Non-empty → the arm cores hold (arm.FaultHold).
    fault: str = ""
    divergence: ShadowDivergence | None = None  # vs the MuJoCo shadow, if one runs
    # (6,) N, N·m: what the scene's contacts exert on the tip's instrument (geoms of contype bit
    # INSTRUMENT on the tip's arm), force and torque about the tip, base frame; None: the backend
    # has no contacts
    contact_wrench: np.ndarray | None = None
    # the same for each of the backend's sites (one tip per arm) by site name, about that site:
    # each arm's own instrument (a two-arm scene); None: the backend has no contacts
    site_wrenches: dict[str, np.ndarray] | None = None


@dataclass(frozen=True)
class SceneReading:
    """What a task scene holds now: its loose objects, who grasps them, the tools' jaws.

    Attributes:
        objects: names of the scene's loose objects (the bodies with a free joint), model order.
        positions: (k, 3) m, each object's body origin, base (world) frame.
        held_by: per object, the arms whose jaws hold it now (both fingers of the arm's tool
            touch it): the tool name without its ``_jaw`` suffix (``"arm1"``), tool order.
        tools: each tool's measured closure from its finger joint, 0 = open … 1 = closed.
        instrument_contact: one arm's instrument (or jaws) touches the other arm now.
        quats: (k, 4) each object's orientation, unit quaternion (x, y, z, w) like
            :attr:`SlaveReading.tip_quat` (a peg standing upright: its z axis up).
    """

    objects: tuple[str, ...]
    positions: np.ndarray
    held_by: tuple[tuple[str, ...], ...]
    tools: dict[str, float]
    instrument_contact: bool
    quats: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))


class SlaveBackend(Protocol):
    """What slave_control needs from a robot."""

    joint_names: tuple[str, ...]
    dt: float  # s: control period of one step
    # True for a real arm (its physics runs by itself: a stall is not replayed, see arm.py);
    # False for a simulation (advanced only by step(): every missed period is replayed)
    realtime: bool

    def command(self, q: np.ndarray) -> None:
        """Set joint position targets (rad), already limited by the caller."""
        ...

    def step(self, n: int = 1) -> None:
        """Advance ``n`` control periods."""
        ...

    def read(self) -> SlaveReading:
        """Current measured state."""
        ...

    def __enter__(self) -> SlaveBackend: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...


#: contype bit of an instrument's contact geoms (robot.xml) and the conaffinity bit of the tissue
#: they touch (scene.xml): the contacts whose forces make the measured tip wrench.
INSTRUMENT = 2

#: actuator group of a tool (a grasper's jaws, robot.xml): not an arm joint. The arm's joints are
#: those driven by the other actuators; :meth:`MujocoBackend.command_tool` drives the tools.
TOOL_GROUP = 2


def contact_wrenches(m: Any, d: Any, mujoco: Any, owner: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(k, 6) force (N) and torque about ``points[i]`` (N·m), base frame, that the contacts exert
    on the instrument geoms (``contype & INSTRUMENT``) of owner ``i`` (``owner[geom]``; -1: no
    one's) — the force a tip sensor on each instrument would measure. Two arms touching each other
    (any of their geoms, a two-arm scene's contact pairs) both feel it, each the push on its own
    geom: the arm pressing is stopped by the same force limit as the arm pressed."""
    out = np.zeros((len(points), 6))
    if d.ncon == 0:
        return out
    f6 = np.empty(6)
    for i in range(d.ncon):
        c = d.contact[i]
        g1, g2 = int(c.geom1), int(c.geom2)
        o1, o2 = int(owner[g1]), int(owner[g2])
        on1, on2 = bool(m.geom_contype[g1] & INSTRUMENT), bool(m.geom_contype[g2] & INSTRUMENT)
        felt: tuple[tuple[int, float], ...]  # (owner, sign of the force on geom2)
        if o1 >= 0 and o2 >= 0 and o1 != o2:  # two arms touch: both feel it
            felt = ((o1, -1.0), (o2, 1.0))
        elif on1 != on2 and (o1 if on1 else o2) >= 0:  # an instrument touches the scene
            felt = ((o1, -1.0),) if on1 else ((o2, 1.0),)
        else:
            continue
        mujoco.mj_contactForce(m, d, i, f6)
        frame = c.frame.reshape(3, 3)  # rows: normal (geom1 → geom2), tangents
        f = frame.T @ f6[:3]  # the force on geom2, world frame
        for k, sign in felt:
            push = sign * f
            out[k, :3] += push
            out[k, 3:] += np.cross(c.pos - points[k], push)
    return out


#: prefix of a scene's port declarations: ``<numeric name="port_<site>" data="k clearance capture"/>``
PORT_PREFIX = "port_"


@dataclass(frozen=True)
class Port:
    """A port in the body wall (a trocar) that an instrument's shaft passes through.

    The wall holds the shaft: once the shaft crosses the port's plane (the plane through the site,
    normal to its z axis; the instrument's far end on the other side), it moves freely within
    ``clearance`` m of the site and beyond it is pushed back towards it with ``stiffness`` N/m ×
    the excess, in the plane — the abdominal wall's lateral push on a trocar. A shaft crossing the
    plane farther than ``capture`` m from the site is not in the port (nothing).
    """

    site: int
    stiffness: float
    clearance: float
    capture: float

    @classmethod
    def declared(cls, m: Any) -> list[Port]:
        """The ports a scene declares (``custom/numeric`` ``port_<site>``: stiffness N/m,
        clearance m, capture m); ConfigError naming the declaration if one is malformed."""
        ports = []
        for i in range(m.nnumeric):
            name = m.numeric(i).name
            if not name.startswith(PORT_PREFIX):
                continue
            site = name[len(PORT_PREFIX) :]
            data = [float(v) for v in m.numeric(i).data]
            if len(data) != 3 or not (data[0] > 0 and 0 <= data[1] < data[2]):
                raise ConfigError(
                    f"scene numeric {name!r} = {data}: need stiffness N/m > 0, 0 <= clearance m < capture m"
                )
            try:
                sid = m.site(site).id
            except KeyError:
                raise ConfigError(f"scene numeric {name!r}: the scene has no site {site!r}") from None
            ports.append(cls(sid, *data))
        return ports

    def force(
        self, site_pos: Sequence[float], normal: Sequence[float], a: Sequence[float], b: Sequence[float]
    ) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
        """(force N, point m) the wall exerts on the shaft from ``a`` to ``b``, base frame; None if
        the shaft is not held by the wall (it does not cross the port's plane, or crosses it
        outside the port). Plain floats: it runs every control period."""
        (ox, oy, oz), (nx, ny, nz) = site_pos, normal
        sa = nx * (a[0] - ox) + ny * (a[1] - oy) + nz * (a[2] - oz)
        sb = nx * (b[0] - ox) + ny * (b[1] - oy) + nz * (b[2] - oz)
        if sa * sb >= 0.0:  # both ends on one side of the wall
            return None
        t = sa / (sa - sb)
        p = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2]))
        ex, ey, ez = p[0] - ox, p[1] - oy, p[2] - oz  # where the shaft crosses the plane, from the site
        en = nx * ex + ny * ey + nz * ez
        ex, ey, ez = ex - en * nx, ey - en * ny, ez - en * nz
        dist = math.sqrt(ex * ex + ey * ey + ez * ez)
        if dist <= self.clearance or dist > self.capture:
            return None
        k = -self.stiffness * (dist - self.clearance) / dist
        return (k * ex, k * ey, k * ez), p


def instrument_owners(m: Any, sites: list[int]) -> np.ndarray:
    """(ngeom,) for each geom, the index in ``sites`` of the arm it is on: the site nearest in the
    body tree (the first ancestor of the geom's body that holds exactly one of the sites); -1 for
    a geom of no one site's arm (the world, a common body of two arms)."""
    parent = m.body_parentid
    holders = []  # per site: its body and every ancestor, up to the world
    for s in sites:
        b, chain = int(m.site_bodyid[s]), set()
        while True:
            chain.add(b)
            if b == 0:
                break
            b = int(parent[b])
        holders.append(chain)
    owner = np.full(m.ngeom, -1, dtype=int)
    for g in range(m.ngeom):
        b = int(m.geom_bodyid[g])
        while True:
            held = [k for k, chain in enumerate(holders) if b in chain]
            if len(held) == 1:
                owner[g] = held[0]
            if held or b == 0:
                break
            b = int(parent[b])
    return owner


class MujocoBackend:
    """MuJoCo physics: position actuators track the commanded joints, 1 ms steps.

    ``read().external_torque`` is the model-based estimate a torque-sensing arm would make: the
    inverse dynamics ``M q̈ + c(q, q̇)`` minus what the model itself explains (actuators, joint
    damping and gravity compensation, constraints). :meth:`push` simulates a hand pushing the
    forceps tip or the wrist (for direct teach); the estimate then equals ``Jᵀ F`` of that push.

    A robot with graspers (actuators of group :data:`TOOL_GROUP`, e.g. the ``vip`` and ``plas``
    jaws ``arm1_jaw``, ``arm2_jaw``) has them in :attr:`tool_names`, driven by :meth:`command_tool`
    and not among the arm's joints; :meth:`read_scene` tells what a task scene's loose objects
    (a peg) do: where they are and which arms hold them.
    """

    def __init__(
        self,
        model: str,
        q_home: tuple[float, ...],
        sites: tuple[str, ...] = (),
        home: tuple[float, ...] = (),
        *,
        scene: str = "",
    ) -> None:
        from telesurg.services.slave_control.models import model_path

        self.scene = model_path(model, scene)  # (scene: one of the robot's scene_*.xml, "" its own)
        self.sites = sites  # extra sites reported in read().site_positions (e.g. one tip per arm)
        self.q_home = np.array(q_home, dtype=float)
        self.home = home  # start pose if q_home is empty and the model has no "home" keyframe
        self.joint_names: tuple[str, ...] = ()
        self.tool_names: tuple[str, ...] = ()  # the group-2 actuators (graspers), model order
        self.dt = 0.001
        self.realtime = False
        self._m: Any = None
        self._d: Any = None
        self._push_force = np.zeros(3)
        self._push_until = 0.0  # sim time (s) at which the push ends
        self._push_at = "tip"
        self._pushes_at = -1.0  # sim time of the ports' pushes applied now

    def __enter__(self) -> MujocoBackend:
        import mujoco

        m = mujoco.MjModel.from_xml_path(str(self.scene))
        d = mujoco.MjData(m)
        # the robot's joints are the ones its arm actuators drive (one position actuator each; a
        # tool's actuator, group TOOL_GROUP, drives a grasper, not an arm joint); an unactuated
        # joint belongs to the scene (the MH3F tissue's indentation, a peg) and is not reported
        joint_act = mujoco.mjtTrn.mjTRN_JOINT
        tools = [a for a in range(m.nu) if int(m.actuator_group[a]) == TOOL_GROUP]
        act_of = {
            int(m.actuator_trnid[a, 0]): a
            for a in range(m.nu)
            if m.actuator_trntype[a] == joint_act and a not in tools
        }
        joints = [j for j in range(m.njnt) if j in act_of] if act_of else list(range(m.njnt))
        self._qadr = np.array([int(m.jnt_qposadr[j]) for j in joints])
        self._dadr = np.array([int(m.jnt_dofadr[j]) for j in joints])
        self.joint_names = tuple(m.joint(j).name for j in joints)
        n = len(joints)
        # the arm's actuators in joint order: ctrl[self._ctrl] = q (a slice when they come first,
        # in joint order, as in every robot.xml here: the 1 kHz command is one copy)
        acts = [act_of[j] for j in joints] if act_of else list(range(m.nu))
        self._ctrl: slice | np.ndarray = slice(0, n) if acts == list(range(n)) else np.array(acts, dtype=int)
        if any(m.actuator_ctrlrange[a, 0] >= m.actuator_ctrlrange[a, 1] for a in tools):
            raise ConfigError(
                f"model {self.scene.parent.name}: a tool actuator (group {TOOL_GROUP}) has no ctrlrange"
            )
        self.tool_names = tuple(m.actuator(a).name for a in tools)
        self._tool_act = {m.actuator(a).name: a for a in tools}
        self._tool_range = {
            m.actuator(a).name: (float(m.actuator_ctrlrange[a, 0]), float(m.actuator_ctrlrange[a, 1]))
            for a in tools
        }
        if len(self.q_home) == 0:  # the model's own start pose: keyframe "home", else `home`
            if "home" in {m.key(i).name for i in range(m.nkey)}:
                mujoco.mj_resetDataKeyframe(m, d, m.key("home").id)
            elif len(self.home) == n:
                d.qpos[self._qadr] = self.home
            self.q_home = d.qpos[self._qadr].copy()
        if len(self.q_home) != n:
            raise ConfigError(f"q_home has {len(self.q_home)} values, model has {n} joints")
        d.qpos[self._qadr] = self.q_home
        d.ctrl[self._ctrl] = self.q_home
        mujoco.mj_forward(m, d)
        self.dt = float(m.opt.timestep)
        try:
            self._site_ids = [m.site(n).id for n in self.sites]
        except KeyError as exc:
            raise ConfigError(f"model {self.scene.parent.name}: no site {exc}") from exc
        self._tip = m.site("tip").id if "tip" in _names(m, "site") else self._site_ids[0]
        self._tip_body = int(m.site_bodyid[self._tip])
        self._wrist_body = m.body("link6").id if "link6" in _names(m, "body") else self._tip_body
        self._mq = np.zeros(m.nv)
        # the scene has an instrument that can touch something: measure its contact wrench, each
        # instrument's (the tip's, then each site's: one per arm) about its own site
        self._touches = bool(np.any(m.geom_contype & INSTRUMENT)) and bool(
            np.any(m.geom_conaffinity & INSTRUMENT)
        )
        self._wrench_sites = list(dict.fromkeys([self._tip, *self._site_ids]))
        self._owner = instrument_owners(m, self._wrench_sites)
        self._wrench_names = tuple(m.site(s).name for s in self._wrench_sites)
        # ports in the body wall (a trocar) and the instrument shafts they hold: (geom, body, owner)
        self._ports = Port.declared(m)
        shafts = {int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER)}
        self._shafts = (
            [
                (g, int(m.geom_bodyid[g]), int(self._owner[g]))
                for g in range(m.ngeom)
                if m.geom_contype[g] & INSTRUMENT and int(m.geom_type[g]) in shafts and self._owner[g] >= 0
            ]
            if self._ports
            else []
        )
        self._scene = _SceneIndex(m, mujoco, tools)
        # each tool's fingers (qpos, dof address and how each follows the actuated one) for reset()
        self._tool_rest = [
            (
                a,
                [
                    (int(m.jnt_qposadr[j]), int(m.jnt_dofadr[j]), c0, c1)
                    for j, c0, c1 in _fingers(m, mujoco, a)
                ],
            )
            for a in tools
        ]
        self._m, self._d, self._mj = m, d, mujoco
        return self

    def _port_forces(self) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
        """(owner, body, force N, point m) of each port's push on each instrument shaft now."""
        m, d = self._m, self._d
        out = []
        for port in self._ports:
            site_pos = d.site_xpos[port.site].tolist()
            xm = d.site_xmat[port.site]
            normal = (float(xm[2]), float(xm[5]), float(xm[8]))  # the site's z axis
            for g, body, owner in self._shafts:
                c, gm, h = d.geom_xpos[g].tolist(), d.geom_xmat[g], float(m.geom_size[g][1])
                ax = (float(gm[2]) * h, float(gm[5]) * h, float(gm[8]) * h)  # half the shaft
                a = (c[0] - ax[0], c[1] - ax[1], c[2] - ax[2])
                b = (c[0] + ax[0], c[1] + ax[1], c[2] + ax[2])
                if (fp := port.force(site_pos, normal, a, b)) is not None:
                    out.append((owner, body, np.array(fp[0]), np.array(fp[1])))
        return out

    def _apply_ports(self, pushes: list[tuple[int, int, np.ndarray, np.ndarray]]) -> None:
        """The ports' pushes on the shafts, as forces on their bodies until the next call."""
        d = self._d
        for _, body, _ in self._shafts:
            d.xfrc_applied[body] = 0.0
        for _, body, f, p in pushes:
            d.xfrc_applied[body, :3] += f
            d.xfrc_applied[body, 3:] += np.cross(p - d.xipos[body], f)

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._m = self._d = None

    def command(self, q: np.ndarray) -> None:
        self._d.ctrl[self._ctrl] = q

    def reset(self, q: np.ndarray) -> None:
        """Put the arm at rest at joints ``q`` (rad), commanded to stay there (the shadow's re-sync,
        an episode's start); its tools' fingers at rest where their commands put them."""
        d = self._d
        d.qpos[self._qadr] = q
        d.qvel[self._dadr] = 0.0
        d.ctrl[self._ctrl] = q
        for a, fingers in self._tool_rest:
            target = float(d.ctrl[a])
            for qadr, dadr, c0, c1 in fingers:
                d.qpos[qadr] = c0 + c1 * target
                d.qvel[dadr] = 0.0
        self._mj.mj_forward(self._m, d)

    def command_tool(self, name: str, grip: float) -> None:
        """Drive tool ``name`` (one of :attr:`tool_names`): ``grip`` 0 = fully open … 1 = fully
        closed (clipped to [0, 1]), the low … high end of the tool actuator's ``ctrlrange``. A
        closed grasper squeezes what is between its jaws with the actuator's force limit.

        Raises:
            ConfigError: no tool ``name`` (the message names the valid ones), or ``grip`` is not
                a finite number.
        """
        a = self._tool_act.get(name)
        if a is None:
            raise ConfigError(
                f"no tool {name!r}; valid: {', '.join(self.tool_names) or 'none (the model has no tools)'}"
            )
        g = float(grip)
        if not math.isfinite(g):
            raise ConfigError(f"tool {name!r}: grip {grip!r} must be a number in [0, 1]")
        lo, hi = self._tool_range[name]
        self._d.ctrl[a] = lo + min(1.0, max(0.0, g)) * (hi - lo)

    def read_scene(self) -> SceneReading:
        """The scene's loose objects, who holds them and the tools' closure, now (see
        :class:`SceneReading`). Reads the contacts of the last step: call it after :meth:`step`."""
        return self._scene.read(self._d)

    def push(self, force: np.ndarray, seconds: float, at: str = "tip") -> None:
        """Push with ``force`` (N, base frame) for ``seconds`` of sim time, at the forceps ``tip``
        or at the ``wrist`` (the flange, where a hand grips the arm outside the patient)."""
        if at not in PUSH_POINTS:
            raise ConfigError(f"push at {at!r}: valid points are {', '.join(PUSH_POINTS)}")
        self._push_force = np.asarray(force, dtype=float).copy()
        self._push_until = float(self._d.time) + seconds
        self._push_at = at

    def step(self, n: int = 1) -> None:
        m, d, mj = self._m, self._d, self._mj
        if self._shafts and self._pushes_at != d.time:  # (read() refreshes them every period)
            self._apply_ports(self._port_forces())
            self._pushes_at = float(d.time)
        if self._push_until <= d.time:
            mj.mj_step(m, d, nstep=n)
            return
        for _ in range(n):  # the push acts at the moving tip: recompute it every step
            d.qfrc_applied[:] = 0.0
            if d.time < self._push_until:
                if self._push_at == "tip":
                    point, body = d.site_xpos[self._tip], self._tip_body
                else:
                    point, body = d.xpos[self._wrist_body], self._wrist_body
                mj.mj_applyFT(m, d, self._push_force, np.zeros(3), point, body, d.qfrc_applied)
            mj.mj_step(m, d)
        if d.time >= self._push_until:
            d.qfrc_applied[:] = 0.0

    def read(self) -> SlaveReading:
        m, d, mj = self._m, self._d, self._mj
        quat = np.empty(4)
        mj.mju_mat2Quat(quat, d.site_xmat[self._tip])  # (w, x, y, z)
        mj.mj_mulM(m, d, self._mq, d.qacc)
        tau_ext = (self._mq + d.qfrc_bias - d.qfrc_passive - d.qfrc_actuator - d.qfrc_constraint)[self._dadr]
        sites = self._wrench_sites
        w = contact_wrenches(m, d, mj, self._owner, d.site_xpos[sites]) if self._touches else None
        if w is not None and self._shafts:  # the wall's push is felt like a contact
            pushes = self._port_forces()
            self._apply_ports(pushes)  # (and it acts through the next step)
            self._pushes_at = float(d.time)
            for owner, _, f, p in pushes:
                w[owner, :3] += f
                w[owner, 3:] += np.cross(p - d.site_xpos[sites[owner]], f)
        return SlaveReading(
            d.qpos[self._qadr],
            d.qvel[self._dadr],
            d.actuator_force[self._ctrl].copy(),
            d.site_xpos[self._tip].copy(),
            np.array([quat[1], quat[2], quat[3], quat[0]]),
            float(d.time),
            tau_ext,
            d.site_xpos[self._site_ids].copy() if self._site_ids else None,
            contact_wrench=None if w is None else w[0],
            site_wrenches=None if w is None else dict(zip(self._wrench_names, w, strict=True)),
        )


class _SceneIndex:
    """Which geoms are whose, for :meth:`MujocoBackend.read_scene`: the loose objects' (bodies with
    a free joint), each tool's fingers' and each arm's (the tool's chain of bodies), computed
    once; :meth:`read` then goes through the contacts with numpy."""

    def __init__(self, m: Any, mujoco: Any, tools: list[int]) -> None:
        free = int(mujoco.mjtJoint.mjJNT_FREE)
        bodies = [int(m.jnt_bodyid[j]) for j in range(m.njnt) if int(m.jnt_type[j]) == free]
        self.objects = tuple(m.body(b).name for b in bodies)
        self.bodies = np.array(bodies, dtype=int)
        parent = m.body_parentid
        geom_body = m.geom_bodyid

        def subtree(root: int) -> set[int]:  # root and every body below it
            out = {root}
            for b in range(root + 1, m.nbody):  # (bodies come in depth-first order)
                if int(parent[b]) in out:
                    out.add(b)
            return out

        # a geom's object (index in self.objects), -1: none
        self.geom_object = np.full(m.ngeom, -1, dtype=int)
        for k, b in enumerate(bodies):
            self.geom_object[np.isin(geom_body, list(subtree(b)))] = k
        # each tool's finger joints: the one its actuator drives and those an equality couples to it
        # (finger b mirroring finger a); a finger's geoms: its body's subtree's
        self.tools = tuple(m.actuator(a).name for a in tools)
        self.arms = tuple(n.removesuffix("_jaw") for n in self.tools)
        self.tool_qadr = np.array([int(m.jnt_qposadr[m.actuator_trnid[a, 0]]) for a in tools], dtype=int)
        ranges = np.array([m.actuator_ctrlrange[a] for a in tools], dtype=float).reshape(-1, 2)
        self.tool_lo, self.tool_span = ranges[:, 0], ranges[:, 1] - ranges[:, 0]
        self.geom_finger = np.full(m.ngeom, -1, dtype=int)  # a geom's finger: column in `touch`
        self.finger_tool: list[int] = []  # each finger's tool
        chains = []  # per tool: the bodies of its fingers and all their ancestors
        for t, a in enumerate(tools):
            chain: set[int] = set()
            for j, _, _ in _fingers(m, mujoco, a):
                b = int(m.jnt_bodyid[j])
                self.geom_finger[np.isin(geom_body, list(subtree(b)))] = len(self.finger_tool)
                self.finger_tool.append(t)
                while b != 0:
                    chain.add(b)
                    b = int(parent[b])
            chains.append(chain)
        self.fingers_of = [np.flatnonzero(np.array(self.finger_tool) == t) for t in range(len(tools))]
        # a geom's arm (tool index): the first body up its tree that is in exactly one tool's chain
        # (a link, the shaft, the jaws); -1: the world or a body common to the arms
        self.geom_arm = np.full(m.ngeom, -1, dtype=int)
        for g in range(m.ngeom):
            b = int(geom_body[g])
            while b != 0:
                held = [t for t, chain in enumerate(chains) if b in chain]
                if held:
                    if len(held) == 1:
                        self.geom_arm[g] = held[0]
                    break
                b = int(parent[b])
        self._xyzw = [1, 2, 3, 0]

    def read(self, d: Any) -> SceneReading:
        k, nf = len(self.objects), len(self.finger_tool)
        touch = np.zeros((k, nf), dtype=bool)  # object touched by finger
        contact = False
        if d.ncon:
            geom = d.contact.geom  # (ncon, 2)
            g1, g2 = geom[:, 0], geom[:, 1]
            if k and nf:
                for ga, gb in ((g1, g2), (g2, g1)):
                    obj, fin = self.geom_object[ga], self.geom_finger[gb]
                    hit = (obj >= 0) & (fin >= 0)
                    touch[obj[hit], fin[hit]] = True
            a1, a2 = self.geom_arm[g1], self.geom_arm[g2]
            contact = bool(np.any((a1 >= 0) & (a2 >= 0) & (a1 != a2)))
        held = tuple(
            tuple(arm for t, arm in enumerate(self.arms) if touch[i, self.fingers_of[t]].all())
            for i in range(k)
        )
        closure = np.clip((d.qpos[self.tool_qadr] - self.tool_lo) / self.tool_span, 0.0, 1.0)
        return SceneReading(
            self.objects,
            d.xpos[self.bodies].copy(),
            held,
            dict(zip(self.tools, closure.tolist(), strict=True)),
            contact,
            d.xquat[self.bodies][:, self._xyzw].copy(),
        )


def _fingers(m: Any, mujoco: Any, a: int) -> list[tuple[int, float, float]]:
    """The joints tool actuator ``a`` moves: ``(joint, c0, c1)``, the joint at ``c0 + c1 · q`` when
    the actuated joint is at ``q``: that joint (0, 1), then each joint a linear joint equality
    couples to it (a grasper's finger b mirroring finger a)."""
    j0 = int(m.actuator_trnid[a, 0])
    out = [(j0, 0.0, 1.0)]
    for e in range(m.neq):
        if int(m.eq_type[e]) != int(mujoco.mjtEq.mjEQ_JOINT):
            continue
        j1, j2 = int(m.eq_obj1id[e]), int(m.eq_obj2id[e])  # q1 = c0 + c1 q2 (+ c2 q2² …)
        c0, c1, *rest = (float(v) for v in m.eq_data[e, :5])
        if any(rest) or j1 == j2 or j0 not in (j1, j2):
            continue
        if j2 == j0:
            out.append((j1, c0, c1))
        elif c1 != 0.0:
            out.append((j2, -c0 / c1, 1.0 / c1))
    return out


def _names(m: Any, kind: str) -> set[str]:
    count = {"site": m.nsite, "body": m.nbody}[kind]
    getter = m.site if kind == "site" else m.body
    return {getter(i).name for i in range(count)}
