"""What a robot's code implements and what it is given: the seams between a robot folder and the services.

A robot folder (``shared/robots/<name>/``) imports only ``shared``; the services compose what it
registers (:class:`~telesurg.shared.robots.registry.RobotSpec`):

* **slave-side motions** — :class:`MotionSource`: the slave_control arm core (one per arm, the same
  for every robot) asks its arm's source each control period whether it drives the arm and for the
  joint target; the source sees the core as an :class:`ArmHandle` and the measurements as an
  :class:`ArmReading`. ``RobotSpec.motions(MotionContext)`` makes an arm's source (or None).
* **mapping strategies** — :class:`MappingStrategy`: the mapping service's engage/clutch state
  machine (one per master → slave pair, the same for every robot) composes the strategy of its
  mode: ``RobotSpec.strategies[mode](PairContext)``. The strategy maps the master samples to
  joint setpoints and publishes them; it sees the state machine as a :class:`PairContext`.

Units: joints rad (m for prismatic joints), positions m, frames the robot's ``base`` frame (the
world frame of its MuJoCo scene).

Example (a motion source that never moves the arm)::

    class Still(AttachedSource):
        control_mode = "joint"
        def active(self) -> bool: return False
        ...
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from telesurg.shared.kinematics.transforms import quat_from_matrix
from telesurg.shared.messages import (
    Command,
    CommandReply,
    MasterButtons,
    Message,
    OperatingState,
    SafetyState,
    Sequencer,
)
from telesurg.shared.robots.registry import ArmProfile

if TYPE_CHECKING:
    from telesurg.shared.bus import Node
    from telesurg.shared.teleop.settings import MappingSettings

#: Points of the simulated hand (``MujocoBackend.push``): the forceps tip and the wrist.
PUSH_POINTS = ("tip", "wrist")


class FollowState(Protocol):
    """The arm core's follow/lease state as a motion source reads it."""

    lease_valid: bool  # the watchdog's lease allows motion now
    following: bool  # the arm follows servo_jp (master–slave)
    reason: str  # why it holds ("" = not holding)


class ArmHandle(Protocol):
    """The arm core (``services/slave_control/arm.ArmCore``) as a motion source sees it."""

    lock: threading.Lock  # held by the core around the source's calls (see :class:`MotionSource`)
    estop: str  # the latched e-stop's reason ("" = none)
    q_cmd: np.ndarray  # the arm's last command
    reading: ArmReading | None  # the last reading

    @property
    def ctl(self) -> FollowState: ...

    def event(self, kind: str, text: str, severity: str = "info") -> None:
        """Publish an event for this arm."""
        ...


class SlaveSettings(Protocol):
    """The slave_control config keys a robot's motion source may read."""

    model: str
    backend: str  # the slave backend's name
    robot: dict[str, Any]  # the robot's own knobs (RobotSpec.make_config)
    work_frame_rpy_deg: tuple[float, float, float]  # deg, the laparoscope's view frame
    patient_box_min_mm: tuple[float, float, float]  # mm, base frame: the patient's body
    patient_box_max_mm: tuple[float, float, float]


@dataclass(frozen=True)
class MotionContext:
    """What ``RobotSpec.motions`` is given to make one arm's motion source.

    Attributes:
        cfg: slave_control's config.
        profile: the arm.
        push: the backend's simulated hand (force N (3,), seconds, point), None if it has none.
    """

    cfg: SlaveSettings
    profile: ArmProfile
    push: Callable[[np.ndarray, float, str], None] | None = None


class PairContext(Protocol):
    """The mapping service's engage state machine of one pair, as a mapping strategy sees it.

    Thread safety: the strategy takes :attr:`lock` in its callbacks; the underscored methods
    expect it held. The state machine decides engage/disengage (clutch, operator presence, lease,
    stale streams); the strategy asks :meth:`_may_engage` at the sample it would engage on and
    calls :meth:`_engaged_now` once it took its references.
    """

    lock: threading.Lock
    buttons: MasterButtons | None  # the newest master buttons
    q_meas: np.ndarray | None  # the slave's newest measured joints
    slave_state: OperatingState | None  # the slave's newest operating state
    master_rx: float  # monotonic s of the newest master sample (the strategy sets it)
    scale: float  # the operator's motion scale
    safety_scale: float  # the watchdog's factor on it (the strategy sets it on a safety state)
    # R_ms as [x, y, z, w] for the teleop state (the strategy sets it: rotation_of(r_ms))
    rotation: tuple[float, float, float, float]
    # the slave's nearest joint limit as a wall in the master frame, (n, d) (shared/teleop/limit_wall.py)
    limit_wall: tuple[float, float, float, float]
    reply_seq: Sequencer  # sequence of the replies on mapping/<arm>/command
    ik_failures: int  # counters the service logs at exit (the strategy counts)
    conflated: int
    clamped: int

    @property
    def cfg(self) -> MappingSettings: ...
    @property
    def node(self) -> Node: ...
    @property
    def master(self) -> str: ...
    @property
    def slave(self) -> str: ...
    @property
    def work(self) -> threading.Event:
        """Set it when a master sample waits: the service loop then calls ``process``."""
        ...

    @property
    def following(self) -> bool:
        """Engaged: the slave follows the mapped master."""
        ...

    @property
    def want_engage(self) -> bool:
        """A new clutch press waits to engage at the next master sample."""
        ...

    def _may_engage(self) -> bool:
        """Use up the press; True if the engage may go ahead (else HOLDING and an event)."""
        ...

    def _engaged_now(self, text: str) -> None:
        """The strategy took its references: ENABLED, and an ``engage`` event with ``text``."""
        ...

    def _disengage(self, reason: str, *, operator: bool = False) -> None:
        """Stop following (HOLDING, a ``disengage`` event with ``reason``): a new press engages."""
        ...

    def _publish_state(self) -> None:
        """Publish the teleop state now (after a scale change)."""
        ...

    def grip_command(self) -> float:
        """The jaws' closure (0 open … 1 closed) to send with the next setpoint; -1: none."""
        ...

    def scale_command(self, cmd: Command, describe: str) -> CommandReply:
        """Answer ``state`` and the operator's scale commands (``describe`` leads ``state``)."""
        ...


class MappingStrategy(Protocol):
    """A robot's mapping of one pair: master samples → joint setpoints (``servo_jp``).

    Made by ``RobotSpec.strategies[mode](gate)`` with the pair's :class:`PairContext`. The service
    subscribes :attr:`MASTER_INPUT` to :meth:`on_master`, the watchdog's safety state to
    :meth:`on_safety_state`, serves ``mapping/<arm>/command`` with :meth:`on_command` if the strategy
    has one (:class:`CommandServer`) and the camera pose with ``on_camera_pose`` if it has one
    (:class:`CameraFollower`), and calls :meth:`process` from its loop.
    """

    #: the master stream it maps: (key suffix under master/<arm>/, message type)
    MASTER_INPUT: tuple[str, type[Message]]

    def on_master(self, msg: Any, key: str) -> None:
        """A master sample (zenoh thread): keep it, set ``gate.work``."""
        ...

    def on_safety_state(self, msg: SafetyState, key: str) -> None:
        """The watchdog's safety state (its ``scale``): rescale without a jump."""
        ...

    def process(self) -> None:
        """Map the newest master sample (the service loop): engage if due, publish servo_jp."""
        ...

    def rescaled(self) -> None:
        """The operator's scale changed (lock held): re-anchor so it makes no jump."""
        ...

    def close(self) -> None:
        """The service stops."""
        ...


@runtime_checkable
class CommandServer(Protocol):
    """A strategy that answers the operator's commands on ``mapping/<arm>/command``."""

    def on_command(self, cmd: Command) -> CommandReply: ...


@runtime_checkable
class CameraFollower(Protocol):
    """A strategy that maps in the endoscope camera's view (``camera`` set)."""

    def on_camera_pose(self, msg: Any, key: str) -> None: ...


@runtime_checkable
class ForceFollower(Protocol):
    """A strategy with TDPA's slave passivity controller (``slave_passivity`` set): the mapping
    hands it the slave's contact force (``slave/<arm>/measured_cf``)."""

    def on_contact_force(self, msg: Any, key: str) -> None: ...


@runtime_checkable
class ViewFrameUser(Protocol):
    """A motion source that jogs in the laparoscope's view (``work`` jogs): slave_control hands it
    the camera's pose stream where the site runs a camera."""

    work_frame: Any  # a :class:`telesurg.shared.kinematics.work_frame.WorkFrame`


class MotionError(Exception):
    """A slave-side motion cannot go on (a joint limit, an unreachable pose): it is stopped."""


@dataclass
class ArmReading:
    """One arm's share of a backend reading, and its measured controlled point.

    Attributes:
        position, velocity, effort: the arm's joints (rad or m, rad/s or m/s, N·m or A).
        profile: the arm (its forward kinematics gives :attr:`tip_pose`).
        external_torque: estimated external joint torques, N·m, or None.
        fault: the backend's fault ("" = none).
        contact_wrench: (6,) what the scene's contacts exert on the instrument, force (N) and
            torque about the tip (N·m), base frame; None when the backend measures no contact.
    """

    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    profile: ArmProfile
    external_torque: np.ndarray | None = None
    fault: str = ""
    contact_wrench: np.ndarray | None = None
    _pose: np.ndarray | None = None

    @property
    def tip_pose(self) -> np.ndarray:
        """(4, 4) the controlled point's pose from the FK of ``position``, m, base frame
        (computed when first asked: the control period itself does not need it)."""
        if self._pose is None:
            self._pose = self.profile.pose(self.position)
        return self._pose

    @property
    def tip_position(self) -> np.ndarray:
        """m, base frame, (3,)."""
        out: np.ndarray = self.tip_pose[:3, 3]
        return out

    @property
    def tip_quat(self) -> tuple[float, float, float, float]:
        """Orientation of the controlled point, unit quaternion (x, y, z, w)."""
        x, y, z, w = quat_from_matrix(self.tip_pose[:3, :3]).tolist()
        return (x, y, z, w)


class AttachedSource:
    """The :meth:`MotionSource.attach` half every slave-side motion source shares: it keeps the
    core it is attached to, and :attr:`_core` returns it (an error before :meth:`attach`)."""

    core: ArmHandle | None = None

    def attach(self, core: ArmHandle) -> None:
        self.core = core

    @property
    def _core(self) -> ArmHandle:
        assert self.core is not None, "attach() first"
        return self.core


class MotionSource(Protocol):
    """A slave-side motion of one arm (trocar modes with PTP, jog, teach/playback, ...).

    The core calls every method with its lock held except :meth:`next`, :meth:`braking`,
    :meth:`measure` and :meth:`command` (which take :attr:`ArmHandle.lock` themselves where they
    need it).
    """

    def attach(self, core: ArmHandle) -> None:
        """The core this source drives (its lock, e-stop and node)."""
        ...

    def active(self) -> bool:
        """A slave-side motion is commanded now (it, not servo_jp, drives the arm)."""
        ...

    def blocks_following(self) -> str:
        """Why master-slave following is not allowed now ("" = allowed)."""
        ...

    def next(self, q_cmd: np.ndarray, reading: ArmReading, dt: float) -> np.ndarray:
        """The joint target of this period (the core rate-limits it); raise :class:`MotionError`
        to stop the motion, return ``q_cmd`` to stay."""
        ...

    def reached(self, q_out: np.ndarray, reading: ArmReading) -> None:
        """After the rate limit: the command sent this period (completion events)."""
        ...

    def stop(self, reason: str) -> None:
        """Cancel the motion (lease lost, e-stop, fault); the operator must command it again."""
        ...

    def braking(self, q_cmd: np.ndarray, dt: float, allowed: bool) -> np.ndarray | None:
        """After a stop: this period's target of the stopped motion's controlled stop (a joint PTP
        ramps its speed down along its checked path), or None: stand still. ``allowed`` False
        (e-stop, fault) drops it."""
        ...

    def measure(self, reading: ArmReading, q_cmd: np.ndarray) -> None:
        """Sub-rate (100 Hz) update from the measurements (mode machine, events)."""
        ...

    def follow_keepout(self, q_from: np.ndarray, q_to: np.ndarray) -> tuple[np.ndarray, str]:
        """The followed step ``q_from → q_to`` (one period of ``servo_jp``, any source) clamped
        by the arm's keep-out (the patient's body): the joints allowed and why it was clamped
        ("" = not). Called from the control loop without the lock."""
        ...

    def command(self, cmd: Command) -> tuple[bool, str]:
        """Answer an operator command for this arm."""
        ...

    @property
    def control_mode(self) -> str:
        """``operating_state.control_mode``."""
        ...

    def state_fields(self) -> tuple[float, tuple[float, float, float]]:
        """(RCM error, mm; trocar, m base frame) for ``operating_state``."""
        ...
