"""The MH3F slave (Jinno 2014): one MOTOMAN-MH3F class 6-axis arm holding straight forceps.

Registers robot ``mh3f`` (README.md beside this file): one arm (id configurable, default
``arm1``), joints ``j1 … j6``, controlled point the forceps tip, frame the robot base (= the
scene's world). Mapping modes ``cartesian`` (6-axis IK; trocar IK in trocar mode) and the
generic ``position``; slave-side motions: the trocar control modes, posture adjustment, jog,
direct teach and playback. Knobs: :class:`~telesurg.shared.robots.mh3f.config.Mh3fConfig`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from telesurg.shared.robots.mh3f.config import Mh3fConfig
from telesurg.shared.robots.registry import ArmProfile, FloatArray, RobotSpec, Sketch, register

if TYPE_CHECKING:
    from telesurg.shared.robots.api import MappingStrategy, MotionContext, MotionSource, PairContext

HERE = Path(__file__).resolve().parent


def _mh3f(arm: str) -> tuple[ArmProfile, ...]:
    from telesurg.shared.robots.mh3f import kinematics as mh3f

    g = mh3f.MH3F

    def pose(q: FloatArray) -> FloatArray:
        return mh3f.fk(q, g)

    def jacobian(q: FloatArray) -> FloatArray:
        return mh3f.jacobian(q, g)

    def ik(T: FloatArray, q_near: FloatArray) -> FloatArray:
        return mh3f.ik(T, q_near, g)

    home = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
    names = g.joint_names
    return (ArmProfile(arm, names, names, g.lower, g.upper, g.max_velocity, home, "tip", pose, jacobian, ik),)


def _mh3f_sketch(arm: str, q: FloatArray) -> Sketch:
    """:func:`~telesurg.shared.robots.mh3f.kinematics.fk_frames`: base, J2, J3, J4, wrist centre,
    flange; the forceps from the flange to its tip (TCP)."""
    from telesurg.shared.robots.mh3f.kinematics import fk_frames

    frames = fk_frames(q)
    return Sketch(frames[:6], frames[5:7], None)


def _motions(ctx: MotionContext) -> MotionSource:
    """The trocar modes, PTP posture adjustment, jog, direct teach and playback (:mod:`.motions`)."""
    from telesurg.shared.robots.mh3f.motions import TrocarMotions

    return TrocarMotions(ctx.cfg, ctx.profile, ctx.push)


def _cartesian(gate: PairContext) -> MappingStrategy:
    """The ``cartesian`` mapping (:mod:`.mapping`)."""
    from telesurg.shared.robots.mh3f.mapping import CartesianMapping

    return CartesianMapping(gate)


register(
    RobotSpec(
        "mh3f",
        _mh3f,
        HERE / "scene.xml",
        ("cartesian", "position"),
        "trocar",
        _mh3f_sketch,
        "MOTOMAN-MH3F class 6-axis arm with straight forceps (Jinno 2014)",
        motions=_motions,
        strategies={"cartesian": _cartesian},
        config=Mh3fConfig,
        catch_up=True,
        patient_keepout=True,
    )
)
