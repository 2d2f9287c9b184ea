"""Slave backends behind one interface: the MuJoCo simulation here (a serial device later).

A backend is a context manager that owns the robot: ``command(q)`` sets joint position targets,
``step(n)`` advances it by ``n`` control periods, and ``read()`` returns the measured state.
mujoco is imported lazily inside the MuJoCo backend.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol

import numpy as np

from shared.errors import ConfigError


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
    """

    position: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    tip_position: np.ndarray
    tip_quat: np.ndarray
    sim_time: float


class SlaveBackend(Protocol):
    """What slave_control needs from a robot."""

    joint_names: tuple[str, ...]
    dt: float  # s: control period of one step

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


class MujocoBackend:
    """MuJoCo physics: position actuators track the commanded joints, 1 ms steps."""

    def __init__(self, model: str, q_home: tuple[float, ...]) -> None:
        from services.slave_control.models import model_path

        self.scene = model_path(model)
        self.q_home = np.array(q_home, dtype=float)
        self.joint_names: tuple[str, ...] = ()
        self.dt = 0.001
        self._m: Any = None
        self._d: Any = None

    def __enter__(self) -> MujocoBackend:
        import mujoco

        m = mujoco.MjModel.from_xml_path(str(self.scene))
        d = mujoco.MjData(m)
        self.joint_names = tuple(m.joint(i).name for i in range(m.njnt))
        if len(self.q_home) != m.nq:
            raise ConfigError(f"q_home has {len(self.q_home)} values, model has {m.nq} joints")
        d.qpos[:] = self.q_home
        d.ctrl[:] = self.q_home
        mujoco.mj_forward(m, d)
        self.dt = float(m.opt.timestep)
        self._tip = m.site("tip").id
        self._m, self._d, self._mj = m, d, mujoco
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._m = self._d = None

    def command(self, q: np.ndarray) -> None:
        self._d.ctrl[:] = q

    def step(self, n: int = 1) -> None:
        self._mj.mj_step(self._m, self._d, nstep=n)

    def read(self) -> SlaveReading:
        d = self._d
        quat = np.empty(4)
        self._mj.mju_mat2Quat(quat, d.site_xmat[self._tip])  # (w, x, y, z)
        return SlaveReading(
            d.qpos.copy(),
            d.qvel.copy(),
            d.actuator_force.copy(),
            d.site_xpos[self._tip].copy(),
            np.array([quat[1], quat[2], quat[3], quat[0]]),
            float(d.time),
        )


BACKENDS = ("mujoco",)


def make_backend(kind: str, model: str, q_home: tuple[float, ...]) -> SlaveBackend:
    """The backend registered as ``kind``."""
    if kind == "mujoco":
        return MujocoBackend(model, q_home)
    raise ConfigError(f"slave backend {kind!r} unknown; valid: {', '.join(BACKENDS)}")
