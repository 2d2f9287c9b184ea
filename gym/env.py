"""A telesurg slave as a Gymnasium environment: the services' mapping and slave rules, no bus.

One step is one master sample at ``control_hz``: the action moves the master (a tip displacement
in the master frame; for the PLAS all-joints mapping, master joint increments), the robot's own
mapping strategy — the very object the mapping service composes (``RobotSpec.strategies[mode]``:
the MH3F's Cartesian mapping with the trocar IK about the RCM, PLAS ``all_joints``, VIP ``vip``) —
turns it into a joint setpoint, and the slave follows it as slave_control's arm core does: the
setpoint timeline replayed at 1 kHz by the core's :class:`SetpointInterpolator`, the command moved
at most the joint speed limits per period (:func:`~telesurg.shared.limits.limit_step`), the
MuJoCo scene stepped by :class:`~telesurg.services.slave_control.backends.MujocoBackend`. Time is
simulated (no wall clock anywhere): an episode runs as fast as the host computes it and is the
same for the same seed and actions.

Example::

    import gymnasium as gym
    import telesurg.gym  # registers the environments

    env = gym.make("telesurg/MH3F-Reach-v0")
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from telesurg.services.mapping import MappingConfig, strategy_factory
from telesurg.services.slave_control.backends import MujocoBackend
from telesurg.services.slave_control.control import SetpointInterpolator
from telesurg.shared import robots
from telesurg.shared.keys import Keys
from telesurg.shared.limits import limit_step
from telesurg.shared.messages import (
    CartesianPose,
    Command,
    CommandReply,
    Header,
    JointSetpoint,
    JointState,
    MasterButtons,
    Message,
    OperatingState,
    Sequencer,
)

SITE = "gym"
#: s: the simulated clock's stamps start here (a stamp of 0 means "none" in a setpoint's origin)
EPOCH_S = 1.0
MASTER = "m1"


class _Outlet:
    """A mapping outlet that keeps what was put (no bus)."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.seq = 0
        self.sent = 0
        self.last: Message | None = None

    def header(self) -> Header:
        self.seq += 1
        return Header(self.source, self.seq, time.time_ns())

    def put(self, msg: Message) -> None:
        self.last = msg
        self.sent += 1


class _Node:
    """What a mapping strategy uses of its node: keys, outlets, events (dropped)."""

    def __init__(self) -> None:
        self.keys = Keys(SITE)
        self.service = "mapping"
        self.outlets: dict[str, _Outlet] = {}

    def outlet(self, key: str, control: bool = True) -> _Outlet:
        out = self.outlets[key] = _Outlet(self.service)
        return out

    def event(self, kind: str, text: str, arm: str = "", severity: str = "info") -> None:
        return None


class _Pair:
    """The mapping service's engage state machine reduced to what an environment needs: the pedal
    is pressed at reset and never released; every other engage rule holds (the strategy's own)."""

    def __init__(self, cfg: MappingConfig, slave: str) -> None:
        self.lock = threading.Lock()
        self._cfg, self._node, self._slave = cfg, _Node(), slave
        self._work = threading.Event()
        self.buttons: MasterButtons | None = MasterButtons(Header("master_capture", 0, 0), True, True)
        self.q_meas: np.ndarray | None = None
        self.slave_state: OperatingState | None = None
        self.master_rx = 0.0
        self.scale = cfg.scale
        self.safety_scale = 1.0
        self.rotation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)  # R_ms (set by the strategy)
        self.limit_wall: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # (set by the strategy)
        self.reply_seq = Sequencer("mapping")
        self.ik_failures = self.conflated = self.clamped = 0
        self._following = False
        self._want = True

    @property
    def cfg(self) -> MappingConfig:
        return self._cfg

    @property
    def node(self) -> Any:
        return self._node

    @property
    def master(self) -> str:
        return MASTER

    @property
    def slave(self) -> str:
        return self._slave

    @property
    def work(self) -> threading.Event:
        return self._work

    @property
    def following(self) -> bool:
        return self._following

    @property
    def want_engage(self) -> bool:
        return self._want

    def _may_engage(self) -> bool:
        self._want = False
        return True

    def _engaged_now(self, text: str) -> None:
        self._following = True

    def _disengage(self, reason: str, *, operator: bool = False) -> None:
        self._following, self._want = False, True  # (the pedal stays down: it engages again)

    def _publish_state(self) -> None:
        return None

    def grip_command(self) -> float:
        return -1.0  # (the environment's arms have no jaws)

    def scale_command(self, cmd: Command, describe: str) -> CommandReply:
        return CommandReply(
            self.reply_seq.next(), self._slave, cmd.name, False, "no commands in an environment"
        )


def _choose_gl() -> None:
    """MuJoCo's offscreen GL (EGL, else OSMesa) for the image observation; an error saying what to
    install if neither is there."""
    import os

    from telesurg.services.common import gl_backend

    backend = gl_backend()
    if not backend:
        raise gymnasium.error.DependencyNotInstalled(
            "the image observation renders offscreen with MuJoCo: install libegl1 + libgl1-mesa-dri "
            "(EGL) or libosmesa6, or make the environment with image=False"
        )
    os.environ.setdefault("MUJOCO_GL", backend)
    if backend in ("egl", "osmesa"):
        os.environ.setdefault("PYOPENGL_PLATFORM", backend)


@dataclass(frozen=True)
class RobotTask:
    """One registered environment: the robot, its arm and mapping mode, and how the slave starts."""

    model: str
    mode: str
    arm: str = "arm1"
    scale: float = 1.0  # slave motion / master motion
    inserted_mm: float = 0.0  # > 0: start in trocar mode, the tip this deep beyond the trocar (MH3F)
    insert_axis: tuple[float, float, float] = (0.5, 0.0, -1.0)  # base frame: trocar → tip direction


class TeleopReachEnv(gymnasium.Env[dict[str, np.ndarray], np.ndarray]):
    """Reach a goal point with the slave's tip by moving the master.

    Observation (``Dict``): ``joints`` (the arm's measured joints, rad / m), ``tip`` (the
    controlled point, m, base frame), ``goal`` (m, base frame) and, with ``image=True``, ``image``
    (the scene's endoscope camera, RGB uint8, MuJoCo offscreen: needs EGL or OSMesa). Action
    (``Box(-1, 1)``): the master's displacement this step, × ``max_step_mm`` (a tip displacement in
    the master frame, m) — for the PLAS all-joints mapping the master's joint increments,
    × ``max_step_deg``. Reward: minus the tip–goal distance (m); terminated within ``success_mm``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 25}  # noqa: RUF012 (gymnasium.Env declares it)

    def __init__(
        self,
        task: RobotTask,
        *,
        control_hz: float = 100.0,
        max_step_mm: float = 2.0,
        max_step_deg: float = 0.5,
        goal_radius_mm: float = 20.0,
        success_mm: float = 2.0,
        image: bool = False,
        width: int = 160,
        height: int = 120,
        render_mode: str | None = None,
    ) -> None:
        self.task = task
        self.spec_robot = robots.get(task.model)
        self.profile = robots.arm_profile(task.model, task.arm)
        self.cfg = MappingConfig(
            model=task.model, mode=task.mode, pairs=[f"{MASTER}:{task.arm}"], scale=task.scale
        )
        self.cfg.validate()
        self.make_strategy = strategy_factory(task.model, task.mode)
        # the master stream the strategy maps: a pose (tip displacements) or joints (increments)
        self.joint_master = self.make_strategy(_Pair(self.cfg, task.arm)).MASTER_INPUT[0] == "measured_js"
        self.dt_ctrl = 1.0 / control_hz
        if image or render_mode is not None:
            _choose_gl()
        arms = robots.arms_of(task.model, task.arm)
        self.backend = MujocoBackend(
            task.model, (), tuple(p.tip_site for p in arms), tuple(v for p in arms for v in p.home)
        )
        self.backend.__enter__()
        names = self.backend.joint_names
        self.index = np.array([names.index(j) for j in self.profile.model_joints])
        self.vmax = np.array(self.profile.max_velocity)
        self.lower, self.upper = np.array(self.profile.lower), np.array(self.profile.upper)
        self.q_all0 = self.backend.read().position.copy()
        self.q0, self.trocar = self._start_pose()
        self.n_phys = max(1, round(self.dt_ctrl / self.backend.dt))
        self.max_step = max_step_deg * np.pi / 180 if self.joint_master else max_step_mm / 1e3
        self.goal_radius, self.success = goal_radius_mm / 1e3, success_mm / 1e3
        self.image, self.width, self.height = image, width, height
        self.render_mode = render_mode
        self._renderer: Any = None
        n = len(self.profile.joint_names)
        self.action_space = spaces.Box(-1.0, 1.0, (6 if self.joint_master else 3,), np.float32)
        obs: dict[str, spaces.Space[Any]] = {
            "joints": spaces.Box(
                self.lower.astype(np.float32), self.upper.astype(np.float32), (n,), np.float32
            ),
            "tip": spaces.Box(-5.0, 5.0, (3,), np.float32),
            "goal": spaces.Box(-5.0, 5.0, (3,), np.float32),
        }
        if image:
            obs["image"] = spaces.Box(0, 255, (height, width, 3), np.uint8)
        self.observation_space = spaces.Dict(obs)  # type: ignore[assignment]
        self.pair: _Pair | None = None
        self.strategy: Any = None
        self.t = 0.0
        self.master = np.zeros(6 if self.joint_master else 3)
        self.goal = np.zeros(3)
        self.q_cmd = self.q0.copy()
        self.interp = SetpointInterpolator(0.1)

    # -- set-up
    def _start_pose(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The arm's start joints and its trocar (m, base frame; None: not in trocar mode)."""
        q_home = self.q_all0[self.index]
        if self.task.inserted_mm <= 0:
            return q_home, None
        from telesurg.shared.robots.mh3f.trocar import trocar_ik

        trocar = np.array(self.spec_robot.make_config({}).trocar_mm) / 1e3
        d = np.array(self.task.insert_axis, dtype=float)
        d /= np.linalg.norm(d)
        q = trocar_ik(trocar + self.task.inserted_mm / 1e3 * d, trocar, q_home)
        return np.asarray(q, dtype=float), trocar

    def _set_arm(self, q: np.ndarray) -> None:
        qa = self.q_all0.copy()
        qa[self.index] = q
        self.backend.reset(qa)

    def _measured(self) -> np.ndarray:
        """The arm's joints now (what the backend's reading gives, without its torque estimate)."""
        # (the arm's own qpos addresses: a jaw's fingers may sit between two arms' joints)
        q: np.ndarray = self.backend._d.qpos[self.backend._qadr[self.index]].copy()
        return q

    def _master_msg(self) -> Message:
        h = Header("master_capture", 0, round((self.t + EPOCH_S) * 1e9))
        if self.joint_master:
            return JointState(h, tuple(f"m{i + 1}" for i in range(6)), tuple(float(v) for v in self.master))
        p = self.master
        return CartesianPose(h, "master", (float(p[0]), float(p[1]), float(p[2])))

    def _map(self) -> np.ndarray | None:
        """One master sample through the strategy; the setpoint it published (None: none)."""
        assert self.pair is not None
        pair = self.pair
        with pair.lock:
            pair.q_meas = self._measured()
            if self.trocar is not None:
                pair.slave_state = OperatingState(
                    Header("slave_control", 0, 0), "ENABLED", "trocar", follow=True, trocar=tuple(self.trocar)
                )
        self.strategy.on_master(self._master_msg(), "")
        self.strategy.process()
        out = pair.node.outlets[pair.node.keys.slave(self.task.arm, "servo_jp")]
        sp = out.last
        return np.array(sp.position) if isinstance(sp, JointSetpoint) and sp.follow else None

    # -- gymnasium
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        q_start = self._start_joints(options)
        self._set_arm(q_start)
        self.t = 0.0
        self.master = np.zeros_like(self.master)
        self.q_cmd = q_start.copy()
        self.interp = SetpointInterpolator(0.1)
        self.pair = _Pair(self.cfg, self.task.arm)
        self.strategy = self.make_strategy(self.pair)
        self._map()  # the engage sample: the references, a setpoint where the slave is
        self._push()
        tip0 = self.profile.tip(q_start)
        v = self.np_random.normal(size=3)
        v *= self.goal_radius * self.np_random.uniform(0.3, 1.0) / np.linalg.norm(v)
        self.goal = tip0 + v
        return self._obs(), self._info()

    def _start_joints(self, options: dict[str, Any] | None) -> np.ndarray:
        """The episode's start joints: ``options["joints"]`` (e.g. where a live slave stood when it
        engaged; rad / m, within the limits) or the task's start pose."""
        unknown = sorted(set(options or {}) - {"joints"})
        if unknown:
            raise ValueError(f"reset options {unknown} unknown; valid: joints")
        if not options or options.get("joints") is None:
            return self.q0.copy()
        q = np.asarray(options["joints"], dtype=float).reshape(-1)
        n = len(self.profile.joint_names)
        if q.shape != (n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"reset options joints: {n} finite values expected ({self.profile.joint_names})")
        if np.any(q < self.lower) or np.any(q > self.upper):
            raise ValueError(f"reset options joints {q.tolist()} outside the joint limits")
        return q

    def _push(self) -> None:
        q = self._map() if self.pair is not None else None
        if q is not None:
            self.interp.push(q, self.t, self.t)

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)
        self.master = self.master + a * self.max_step
        dt = self.backend.dt
        self.t += self.dt_ctrl
        self._push()
        # the slave's 1 kHz periods until the next master sample (slave_control's arm core while
        # following: the interpolated reference, at most the joint speed limits per period)
        t_phys = self.t - self.dt_ctrl
        m, d, mj = self.backend._m, self.backend._d, self.backend._mj
        for _ in range(self.n_phys):
            t_phys += dt
            ref = self.interp.sample(t_phys)
            if ref is not None:
                self.q_cmd = self.q_cmd + limit_step(ref - self.q_cmd, self.vmax * dt)
            d.ctrl[self.index] = self.q_cmd
            mj.mj_step(m, d)
        obs = self._obs()
        info = self._info()
        dist = info["distance_m"]
        return obs, -dist, dist < self.success, False, info

    def _obs(self) -> dict[str, np.ndarray]:
        q = self._measured()
        self._tip_now = np.asarray(self.profile.tip(q), dtype=float)
        out = {
            "joints": np.clip(q, self.lower, self.upper).astype(np.float32),
            "tip": self._tip_now.astype(np.float32),
            "goal": self.goal.astype(np.float32),
        }
        if self.image:
            out["image"] = self._render()
        return out

    def _info(self) -> dict[str, Any]:
        """(after :meth:`_obs`)"""
        tip = self._tip_now
        info: dict[str, Any] = {
            "t": self.t,
            "tip_m": tip,
            "distance_m": float(np.linalg.norm(tip - self.goal)),
        }
        if self.pair is not None:
            info["ik_failures"] = self.pair.ik_failures
        return info

    def _render(self) -> np.ndarray:
        import mujoco

        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.backend._m, self.height, self.width)
        m = self.backend._m
        cam = next((i for i in range(m.ncam)), -1)
        self._renderer.update_scene(self.backend._d, camera=cam)
        img: np.ndarray = self._renderer.render()
        return img

    def render(self) -> np.ndarray | None:
        return self._render() if self.render_mode == "rgb_array" else None

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self.backend.__exit__(None, None, None)
