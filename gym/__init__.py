"""``telesurg.gym``: Gymnasium environments of the telesurg slaves (``docs/learning.md``).

Importing it registers, per robot and task:

* ``telesurg/MH3F-Reach-v0`` — the MH3F forceps through the trocar (trocar IK about the RCM),
* ``telesurg/PLAS-Reach-v0`` — a PLAS arm, the all-joints mapping (master joint increments),
* ``telesurg/VIP-Reach-v0`` — a VIP arm through its virtual incision port.

Each is :class:`~telesurg.gym.env.TeleopReachEnv` with the robot's own mapping strategy and the
slave core's following rules, 200 steps of 10 ms. Keyword arguments of ``gymnasium.make`` reach
the environment (``image=True`` adds the endoscope image; ``control_hz``, ``max_step_mm``, ...).

Example::

    import gymnasium as gym
    import telesurg.gym

    env = gym.make("telesurg/VIP-Reach-v0", image=False)
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry
from telesurg.gym.env import RobotTask, TeleopReachEnv

__all__ = ["ENVIRONMENTS", "RobotTask", "TeleopReachEnv"]

#: id → the robot task it runs
ENVIRONMENTS: dict[str, RobotTask] = {
    "telesurg/MH3F-Reach-v0": RobotTask("mh3f", "cartesian", inserted_mm=100.0),
    "telesurg/PLAS-Reach-v0": RobotTask("plas", "all_joints"),
    "telesurg/VIP-Reach-v0": RobotTask("vip", "vip"),
}
MAX_STEPS = 200

for _id, _task in ENVIRONMENTS.items():
    if _id not in registry:
        register(
            id=_id,
            entry_point="telesurg.gym.env:TeleopReachEnv",
            kwargs={"task": _task},
            max_episode_steps=MAX_STEPS,
        )
