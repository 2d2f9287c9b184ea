"""The robot registry: every slave robot the services can drive, described once and found by name.

A robot is one :class:`RobotSpec` registered under its name (:func:`register`, :func:`get`,
:func:`names`): its arms (an :class:`ArmProfile` each: joint names, limits, speeds, home, the
MuJoCo tip site, FK as :meth:`ArmProfile.pose`, the Jacobian, an optional IK), its MuJoCo scene,
its config dataclass (the robot's own knobs, :meth:`RobotSpec.make_config`), its mapping
strategies by mode name, its slave-side motion sources and what the mirror draws of it
(:meth:`RobotSpec.sketch`). Services take the robot from here and never compare robot names.
More robots come from plugins: :func:`load_plugin` imports a Python file (every service's
``--plugin FILE``) whose import calls :func:`register` (docs/extending.md, "Add a robot").

Frame convention (one for every robot): :meth:`ArmProfile.pose` is the pose ``(4, 4)`` of the
arm's controlled point in the **world frame of the robot's MuJoCo scene**, equal to the pose of
the MuJoCo site :attr:`ArmProfile.tip_site` (``site_xpos``, ``site_xmat``). :meth:`ArmProfile.jacobian`
is the geometric Jacobian ``(6, n)`` of that point in the same frame: ``[v; ω] = J @ qdot``, rows
``v`` (m/s) then ``ω`` (rad/s), world coordinates; ``qdot`` in rad/s (m/s for prismatic joints).

Example::

    from telesurg.shared import robots
    robots.get("mh3f").arm("arm1").pose(robots.get("mh3f").arm("arm1").home)
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import pathlib
import re
import sys
import textwrap
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cache
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import ConfigError, IKError

if TYPE_CHECKING:
    from telesurg.shared.kinematics.elbow import ElbowChain

FloatArray = npt.NDArray[np.float64]

#: Slave motion families, a description for listings (the services go by ``motions``,
#: ``catch_up`` and ``patient_keepout``, never by the family): ``trocar`` — a 6-axis forceps arm with
#: the trocar modes; ``joint`` — joint-space arms.
SLAVE_FAMILIES = ("trocar", "joint")

_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}")


@dataclass(frozen=True)
class ArmProfile:
    """One arm of a robot model.

    Attributes:
        arm: arm id used in keys (``slave/<arm>/…``).
        joint_names: the arm's joint names in messages.
        model_joints: the same joints' names in the MuJoCo model.
        lower, upper: joint limits (rad, or m for prismatic joints).
        max_velocity: joint speed limits (rad/s or m/s).
        home: start pose.
        tip_site: MuJoCo site of the controlled point.
        pose_of: joints ``(n,)`` → pose ``(4, 4)`` of the controlled point (module docstring).
        jacobian_of: joints ``(n,)`` → geometric Jacobian ``(6, n)`` (module docstring).
        ik_of: optional analytic IK, (target pose ``(4, 4)``, joints to stay near ``(n,)``) →
            joints ``(n,)``, raising :class:`~telesurg.shared.errors.IKError`; None: no IK.
        elbow: optional redundancy of an arm whose controlled point hangs from an elbow
            (:class:`~telesurg.shared.kinematics.elbow.ElbowChain`, the VIP arms): slave_control
            offers the elbow (null-space) jog on such an arm; None: no elbow.

    Raises:
        ConfigError: the tuples differ in length, a limit is not finite or ``lower > upper``,
            a speed is not positive, or ``home`` is outside the limits.
    """

    arm: str
    joint_names: tuple[str, ...]
    model_joints: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    max_velocity: tuple[float, ...]
    home: tuple[float, ...]
    tip_site: str
    pose_of: Callable[[FloatArray], FloatArray]
    jacobian_of: Callable[[FloatArray], FloatArray]
    ik_of: Callable[[FloatArray, FloatArray], FloatArray] | None = None
    elbow: ElbowChain | None = None

    def __post_init__(self) -> None:
        n = len(self.joint_names)
        what = f"arm {self.arm!r}"
        if n == 0:
            raise ConfigError(f"{what} has no joints")
        fields = ("model_joints", "lower", "upper", "max_velocity", "home")
        for name in fields:
            if len(getattr(self, name)) != n:
                raise ConfigError(f"{what}: {name} has {len(getattr(self, name))} values, not {n}")
        for j, lo, hi, v, h in zip(
            self.joint_names, self.lower, self.upper, self.max_velocity, self.home, strict=True
        ):
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ConfigError(f"{what}: joint {j} limits [{lo}, {hi}] must be finite, lower <= upper")
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError(f"{what}: joint {j} max_velocity {v} must be > 0")
            if not lo <= h <= hi:
                raise ConfigError(f"{what}: joint {j} home {h} outside [{lo}, {hi}]")

    def pose(self, q: npt.ArrayLike) -> FloatArray:
        """Pose ``(4, 4)`` of the controlled point (world frame of the scene, = the tip site)."""
        return np.asarray(self.pose_of(np.asarray(q, dtype=np.float64)), dtype=np.float64)

    def jacobian(self, q: npt.ArrayLike) -> FloatArray:
        """Geometric Jacobian ``(6, n)`` of :meth:`pose`: ``[v; ω] = J @ qdot`` (world frame)."""
        return np.asarray(self.jacobian_of(np.asarray(q, dtype=np.float64)), dtype=np.float64)

    def tip(self, q: npt.ArrayLike) -> FloatArray:
        """Position ``(3,)`` [m] of the controlled point (world frame of the scene)."""
        out: FloatArray = self.pose(q)[:3, 3].copy()
        return out

    def ik(self, target: npt.ArrayLike, q_near: npt.ArrayLike) -> FloatArray:
        """Joints placing the controlled point at pose ``target``, nearest ``q_near``.

        Raises:
            IKError: the arm has no analytic IK, or the target has no valid solution.
        """
        if self.ik_of is None:
            raise IKError(f"arm {self.arm!r} has no analytic IK")
        T = np.asarray(target, dtype=np.float64)
        return np.asarray(self.ik_of(T, np.asarray(q_near, dtype=np.float64)), dtype=np.float64)


class Sketch(NamedTuple):
    """What the mirror draws of one slave arm, in the scene's world frame [m].

    ``links`` (N, 3): the kinematic chain; ``forceps`` (M, 3) or None: the instrument (tool
    segment); ``rcm`` (3,) or None: the mechanism's own remote centre of motion (vip R).
    """

    links: FloatArray
    forceps: FloatArray | None
    rcm: FloatArray | None


@dataclass(frozen=True)
class RobotSpec:
    """One robot, as the services see it.

    Attributes:
        name: registry name (the services' ``model`` config key): lowercase letters, digits, ``_``.
        arms: arm id → the robot's arms. A single-arm robot names its one arm by the id it is
            given (the slave_control ``arm`` key); a multi-arm robot ignores it.
        scene: the MuJoCo ``scene.xml`` the ``mujoco`` backend loads (joint names = the arms'
            ``model_joints``, one position actuator per joint).
        mapping_modes: the mapping modes (``mapping.mode``) that fit this robot.
        slave_family: one of :data:`SLAVE_FAMILIES`.
        sketch: (arm id, joints) → :class:`Sketch`, what the mirror draws.
        description: one line for listings.
        config: the robot's config dataclass (its own knobs, the ``robot`` table of the mapping
            and slave_control configs; every field has a default), or None: no knobs.
        strategies: mapping mode → factory of the robot's own mapping strategy
            (:class:`~telesurg.shared.robots.api.MappingStrategy`); a mode in
            :attr:`mapping_modes` without a factory is a generic mode of the mapping service
            (``position``).
        motions: factory of an arm's slave-side motion source
            (:class:`~telesurg.shared.robots.api.MotionSource`), or None for an arm that follows
            ``servo_jp`` only (the factory may return None for such an arm too).
        catch_up: an arm of this robot makes up a stall of its setpoint timeline at up to 2× the
            master's pace (the MH3F: its servos must stay on the trocar's RCM); False: the arm
            keeps its timeline (the joint-space arms).
        patient_keepout: the watchdog checks the arm against the patient's body (the MH3F forceps
            arm above its torso, :mod:`telesurg.shared.robots.mh3f.keepout`).
    """

    name: str
    arms: Callable[[str], tuple[ArmProfile, ...]]
    scene: pathlib.Path
    mapping_modes: tuple[str, ...]
    slave_family: str
    sketch: Callable[[str, FloatArray], Sketch]
    description: str = ""
    config: type[Any] | None = None
    strategies: Mapping[str, Callable[..., Any]] = field(default_factory=dict)
    motions: Callable[..., Any] | None = None
    catch_up: bool = False
    patient_keepout: bool = False

    def scene_variants(self) -> tuple[str, ...]:
        """The other scenes this robot ships beside ``scene``: the ``scene_*.xml`` files in its
        folder (a task's scene, e.g. the MH3F's ``scene_trocar_task.xml``), sorted."""
        return tuple(sorted(p.name for p in self.scene.parent.glob("scene_*.xml")))

    def scene_file(self, variant: str = "") -> pathlib.Path:
        """The MuJoCo scene: ``scene``, or its ``variant`` (a name from :meth:`scene_variants`).

        Raises:
            ConfigError: ``variant`` is not one of them (the message lists the valid ones).
        """
        if not variant:
            return self.scene
        if variant not in (valid := self.scene_variants()):
            raise ConfigError(
                f"robot {self.name!r} has no scene {variant!r}; valid: {', '.join(valid) or 'none'} "
                "(the scene_*.xml files in its folder), or empty for its own scene"
            )
        return self.scene.parent / variant

    def __post_init__(self) -> None:
        if not _NAME.fullmatch(self.name):
            raise ConfigError(f"robot name {self.name!r} must match {_NAME.pattern}")
        if self.slave_family not in SLAVE_FAMILIES:
            raise ConfigError(
                f"robot {self.name!r}: slave_family {self.slave_family!r} invalid; "
                f"valid: {', '.join(SLAVE_FAMILIES)}"
            )
        if not self.mapping_modes:
            raise ConfigError(f"robot {self.name!r} names no mapping mode")
        if not pathlib.Path(self.scene).is_file():
            raise ConfigError(f"robot {self.name!r}: scene {self.scene} is not a file")
        extra = sorted(set(self.strategies) - set(self.mapping_modes))
        if extra:
            raise ConfigError(f"robot {self.name!r}: strategies for modes {extra} not in mapping_modes")
        if self.config is not None and not dataclasses.is_dataclass(self.config):
            raise ConfigError(f"robot {self.name!r}: config {self.config!r} is not a dataclass")

    def make_config(self, data: Mapping[str, Any] | None = None) -> Any:
        """The robot's config from a ``robot`` table (``{}``: the defaults), type-checked; None for a
        robot without knobs.

        Raises:
            ConfigError: an unknown key (the message lists the valid ones) or a wrong type.
        """
        from telesurg.shared.config import from_dict

        if self.config is None:
            if data:
                raise ConfigError(f"robot {self.name!r} has no config keys; got {', '.join(sorted(data))}")
            return None
        return from_dict(self.config, dict(data or {}), "robot")

    def arm(self, arm: str) -> ArmProfile:
        """The profile of ``arm`` (a single-arm robot takes any arm id).

        Raises:
            ConfigError: the robot has no arm of that id (the message lists its arms).
        """
        with _LOCK:
            registered = _REGISTRY.get(self.name) is self
        arms = arms_of(self.name, arm) if registered else self.arms(arm)  # (cached when registered)
        for a in arms:
            if a.arm == arm:
                return a
        raise ConfigError(
            f"robot model {self.name!r} has no arm {arm!r}; arms: {', '.join(a.arm for a in arms)}"
        )


_REGISTRY: dict[str, RobotSpec] = {}
_PLUGINS: dict[pathlib.Path, str] = {}  # resolved plugin path → its module name
_LOCK = threading.Lock()


def register(spec: RobotSpec) -> None:
    """Add ``spec`` to the registry.

    Raises:
        ConfigError: another robot of that name is registered already.
    """
    with _LOCK:
        old = _REGISTRY.get(spec.name)
        if old is not None and old != spec:
            raise ConfigError(f"robot {spec.name!r} is registered already")
        _REGISTRY[spec.name] = spec
        arms_of.cache_clear()


def names() -> tuple[str, ...]:
    """The registered robot names, sorted."""
    with _LOCK:
        return tuple(sorted(_REGISTRY))


def get(name: str) -> RobotSpec:
    """The robot registered as ``name``.

    Raises:
        ConfigError: no such robot; the message lists the valid names.
    """
    with _LOCK:
        spec = _REGISTRY.get(name)
    if spec is None:
        raise ConfigError(f"robot model {name!r} unknown; valid: {', '.join(names())}")
    return spec


def load_plugin(path: str) -> None:
    """Import the Python file ``path``, whose import registers robots (:func:`register`).

    Loading the same file again does nothing.

    Raises:
        ConfigError: the file does not exist, or importing it failed (the cause is chained).
    """
    file = pathlib.Path(path).expanduser().resolve()
    with _LOCK:
        if file in _PLUGINS:
            return
    if not file.is_file():
        raise ConfigError(f"robot plugin {path!r}: no such file")
    module = f"telesurg_plugin_{len(_PLUGINS)}_{re.sub(r'[^0-9A-Za-z_]', '_', file.stem)}"
    spec = importlib.util.spec_from_file_location(module, file)
    if spec is None or spec.loader is None:
        raise ConfigError(f"robot plugin {path!r}: not a Python file")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[module] = mod
    try:
        spec.loader.exec_module(mod)
    except Exception as exc:
        del sys.modules[module]
        raise ConfigError(f"robot plugin {path!r} failed to load: {type(exc).__name__}: {exc}") from exc
    with _LOCK:
        _PLUGINS[file] = module


@cache
def arms_of(model: str, arm: str = "arm1") -> tuple[ArmProfile, ...]:
    """The arms of ``model`` (``arm``: the id of a single-arm model's arm).

    Raises:
        ConfigError: unknown model (the message lists the valid ones).
    """
    arms = get(model).arms(arm)
    if not arms:
        raise ConfigError(f"robot model {model!r} has no arms")
    return arms


def arm_profile(model: str, arm: str) -> ArmProfile:
    """The profile of ``arm`` in ``model`` (single-arm models take any arm id)."""
    return get(model).arm(arm)


def recognise(arm: str, joint_names: tuple[str, ...]) -> tuple[RobotSpec, ArmProfile] | None:
    """(robot, profile) of the registered robot whose arm ``arm`` has exactly these joint names.

    The first match in name order, or None.
    """
    for name in names():
        try:
            profile = get(name).arm(arm)
        except ConfigError:  # the robot has no arm of that id (plas / vip: arm1, arm2)
            continue
        if profile.joint_names == joint_names:
            return get(name), profile
    return None


def two_arms(make: Callable[[str], ArmProfile]) -> Callable[[str], tuple[ArmProfile, ...]]:
    """The arms of a two-arm robot (``arm1``, ``arm2``; the arm id it is given is ignored)."""

    def arms(arm: str) -> tuple[ArmProfile, ...]:
        return (make("arm1"), make("arm2"))

    return arms


def config_help() -> str:
    """The ``--help`` text of the ``robot`` table: every registered robot's knobs (its config)."""
    from telesurg.shared.config import field_docs

    lines = ["robot keys (the `robot` table: --set robot.KEY=VALUE; the model's own config):"]
    for name in names():
        cls = get(name).config
        if cls is None:
            continue
        lines.append(f"  model {name}:")
        for d in field_docs(cls, "robot."):
            unit = f" [{d.unit}]" if d.unit else ""
            lines.append(
                f"    {d.key}  (table)"
                if d.type == "table"
                else f"    {d.key} : {d.type} = {d.default}{unit}"
            )
            lines += [f"        {w}" for w in textwrap.wrap(d.help, 92)]
    return "\n".join(lines)
