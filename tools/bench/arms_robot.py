"""``mh3f_x<N>``: N MH3F arms in one robot, for ``telesurg bench arms`` (a plugin robot).

The MuJoCo model is N copies of the MH3F (``shared/robots/mh3f/robot.xml``) attached at the
same base, each prefixed ``arm<i>_`` (joints ``arm<i>_j1 …``, tip site ``arm<i>_tip``); the arms
have no contact geoms between them, so they overlap without colliding. Each arm is the MH3F's
profile (its FK, Jacobian, IK and limits) under arm id ``arm<i>``, mapped by the MH3F's
``cartesian`` mapping; no slave-side motions (the arms follow their master). A bench site drives
it as a robot with N identical arms: one slave_control loop steps all of them, one mapping maps
every pair, one watchdog watches every arm.

Example (the plugin file the bench writes)::

    from pathlib import Path
    from telesurg.tools.bench.arms_robot import register_arms
    register_arms(4, Path(__file__).parent)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from telesurg.shared.robots import registry
from telesurg.shared.robots.registry import RobotSpec

ROBOT_XML = Path(__file__).resolve().parents[2] / "shared" / "robots" / "mh3f" / "robot.xml"


def robot_name(n: int) -> str:
    """The registry name of the N-arm robot."""
    return f"mh3f_x{n}"


def write_scene(n: int, out_dir: Path) -> Path:
    """The MuJoCo scene of N MH3F arms at one base (module doc), written to ``out_dir``."""
    import mujoco

    spec = mujoco.MjSpec()
    spec.modelname = robot_name(n)
    spec.option.timestep = 0.001
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    for i in range(1, n + 1):
        arm = mujoco.MjSpec.from_file(str(ROBOT_XML))
        spec.worldbody.add_frame().attach_body(arm.worldbody.first_body(), f"arm{i}_", "")
    spec.compile()  # (a clear error here rather than in the slave)
    path = out_dir / f"{robot_name(n)}.xml"
    path.write_text(spec.to_xml())
    return path


def register_arms(n: int, out_dir: Path) -> str:
    """Register ``mh3f_x<n>`` (writing its scene to ``out_dir`` if absent); returns its name."""
    if not 1 <= n <= 16:
        raise ValueError(f"arms: {n} outside [1, 16]")
    name = robot_name(n)
    if name in registry.names():
        return name
    scene = out_dir / f"{name}.xml"
    if not scene.is_file():
        scene = write_scene(n, out_dir)
    mh3f = registry.get("mh3f")
    one = mh3f.arm("arm1")

    def arms(_: str) -> tuple[registry.ArmProfile, ...]:
        return tuple(
            dataclasses.replace(
                one,
                arm=f"arm{i}",
                model_joints=tuple(f"arm{i}_{j}" for j in one.model_joints),
                tip_site=f"arm{i}_tip",
            )
            for i in range(1, n + 1)
        )

    registry.register(
        RobotSpec(
            name,
            arms,
            scene,
            ("cartesian",),
            "joint",
            mh3f.sketch,
            f"{n} MH3F arms at one base (telesurg bench arms)",
            config=mh3f.config,
            strategies={"cartesian": mh3f.strategies["cartesian"]},
        )
    )
    return name
