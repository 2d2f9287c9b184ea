"""The VIP slave (Jang 2014): two conical-RCM arms with an elbow, driven by the virtual incision port.

Registers robot ``vip`` (README.md beside this file): arms ``arm1``/``arm2``, joints ``q1 … q5``,
controlled point the wrist W in the port frame. Mapping modes ``vip`` (master tip → wrist, elbow on
the line wrist–VIP) and the generic ``position``; slave-side motion: the elbow (null-space) jog.
Knobs: :class:`~telesurg.shared.robots.vip.config.VipConfig`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from telesurg.shared.robots.registry import ArmProfile, FloatArray, RobotSpec, Sketch, register, two_arms
from telesurg.shared.robots.vip.config import VipConfig

if TYPE_CHECKING:
    from telesurg.shared.robots.api import MappingStrategy, MotionContext, MotionSource, PairContext

HERE = Path(__file__).resolve().parent

#: VIP arm joint speeds (the paper gives none): 2 rad/s, 0.1 m/s for the prismatic q3.
VIP_MAX_VELOCITY = (2.0, 2.0, 0.1, 2.0, 2.0)


def _vip_arm(arm: str) -> ArmProfile:
    from telesurg.shared.kinematics.elbow import ElbowChain
    from telesurg.shared.robots.vip import kinematics as vip

    geom = vip.VIP_ARM1 if arm == "arm1" else vip.VIP_ARM2

    def pose(q: FloatArray) -> FloatArray:
        return vip.fk(q, geom).wrist_frame

    def jacobian(q: FloatArray) -> FloatArray:
        return vip.wrist_jacobian(q, geom)

    def elbow(q: FloatArray) -> FloatArray:
        return vip.fk(q, geom).elbow

    def wrist(q: FloatArray) -> FloatArray:
        return vip.fk(q, geom).wrist

    def solve(E: FloatArray, W: FloatArray, q_near: FloatArray) -> FloatArray:
        return vip.ik(E, W, geom, q4_ref=float(q_near[3]))

    names = geom.joint_names
    return ArmProfile(
        arm,
        names,
        tuple(f"{arm}_{n}" for n in names),
        geom.lower,
        geom.upper,
        VIP_MAX_VELOCITY,
        geom.home,
        f"{arm}_wrist",
        pose,
        jacobian,
        elbow=ElbowChain(elbow, wrist, solve, geom.lower, geom.upper),
    )


def _vip_sketch(arm: str, q: FloatArray) -> Sketch:
    """:func:`telesurg.shared.robots.vip.kinematics.fk`: R–E–W; the RCM is R."""
    from telesurg.shared.robots.vip import kinematics as vip

    pose = vip.fk(q, vip.VIP_ARM1 if arm == "arm1" else vip.VIP_ARM2)
    return Sketch(np.stack([pose.rcm, pose.elbow, pose.wrist]), None, pose.rcm)


def _motions(ctx: MotionContext) -> MotionSource | None:
    """The elbow (null-space) jog of an arm with an elbow (:mod:`.elbow_jog`)."""
    from telesurg.shared.robots.vip.elbow_jog import ElbowJog

    return ElbowJog(ctx.cfg, ctx.profile) if ctx.profile.elbow is not None else None


def _vip(gate: PairContext) -> MappingStrategy:
    """The ``vip`` mapping (:mod:`.mapping`)."""
    from telesurg.shared.robots.vip.mapping import VipMapping

    return VipMapping(gate)


register(
    RobotSpec(
        "vip",
        two_arms(_vip_arm),
        HERE / "scene.xml",
        ("vip", "position"),
        "joint",
        _vip_sketch,
        "two conical-RCM arms with an elbow, VIP control (Jang 2014)",
        motions=_motions,
        strategies={"vip": _vip},
        config=VipConfig,
    )
)
