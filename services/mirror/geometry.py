"""The slave robot's own geometry, read from its MuJoCo model and posed from the measured joints.

The mirror draws each slave robot as MuJoCo models it: every visible geom of every robot body
(boxes, spheres/ellipsoids, capsules, cylinders as rerun primitives; mesh geoms as triangle
meshes). The primitives' sizes and colours are sent once; per drawn frame their world poses
(:meth:`RobotGeometry.primitive_poses`) go out together, one row of one entity per robot. Meshes
are sent once per body in the body's own frame and posed per frame by each moved body's pose
(:meth:`RobotGeometry.pose`, one ``Transform3D``). The poses come from MuJoCo's forward
kinematics (``mj_kinematics``) on the mirror's own copy of the robot's scene, with the arms'
joints set from their latest ``measured_js`` — the same kinematics the slave simulation runs.

The robot and its scene come from the robot registry (:mod:`telesurg.shared.robots`, a plugin's
robot included); nothing here knows a robot by name. What is drawn: the bodies of the scene other
than the world body (the table, the patient and the floor are scene, not robot) and mocap bodies
(moved by other services, e.g. the endoscope holder), their geoms of the visible groups 0–2 with
a non-zero alpha. Arms not yet measured are drawn at the model's reference pose.

Pure apart from MuJoCo (imported lazily): numpy in, numpy out, no I/O but reading the scene.

Example::

    geo = RobotGeometry.load(robots.get("mh3f"))
    poses = geo.pose({"arm1": (profile, q)})   # body name → (position (3,), quaternion wxyz (4,))
    prims = geo.primitive_poses({"arm1": (profile, q)})  # kind → (centres (N, 3), quaternions (N, 4))
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from telesurg.shared.errors import ConfigError
from telesurg.shared.robots import ArmProfile, RobotSpec

FloatArray = npt.NDArray[np.float64]
Rgba = tuple[int, int, int, int]

#: Geom groups drawn (MuJoCo's viewers show 0–2 by default; 3+ are collision / hidden by convention).
VISIBLE_GROUPS = (0, 1, 2)
#: Primitive kinds (rerun archetype: Boxes3D, Ellipsoids3D, Capsules3D, Cylinders3D).
KINDS = ("box", "ellipsoid", "capsule", "cylinder")
#: A body whose pose moved less than this (m, and rad of rotation as quaternion distance) since it
#: was last sent is not sent again.
POSE_EPS = 1e-6


@dataclass(frozen=True)
class Primitive:
    """One primitive geom in its body's frame.

    ``size``: box and ellipsoid: the half sizes (3,) [m]; capsule and cylinder: (radius, length
    between the end-cap centres / of the side) [m] (2,). ``center`` (3,) [m] and ``quat`` (4,) w x y z:
    the geom's centre and orientation in the body frame (the capsule's and cylinder's axis is its z).
    """

    kind: str
    size: FloatArray
    center: FloatArray
    quat: FloatArray
    rgba: Rgba
    geom: int = -1  # the geom's index in the model (-1: not from a model)


@dataclass(frozen=True)
class MeshPart:
    """One mesh geom: ``vertices`` (V, 3) [m] and ``faces`` (F, 3) already in the body frame."""

    vertices: FloatArray
    faces: npt.NDArray[np.uint32]
    rgba: Rgba


@dataclass(frozen=True)
class Body:
    """A drawn body: its name in the model, its index, its primitives and meshes (body frame)."""

    name: str
    index: int
    primitives: tuple[Primitive, ...]
    meshes: tuple[MeshPart, ...]


def quat_matrix(q: FloatArray) -> FloatArray:
    """Rotation matrix (3, 3) of a unit quaternion w x y z."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rgba(model: Any, g: int) -> Rgba:
    mat = int(model.geom_matid[g])
    c = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]
    r, gr, b, a = (round(255 * float(np.clip(v, 0.0, 1.0))) for v in c)
    return (r, gr, b, a)


class RobotGeometry:
    """The drawable bodies of one robot's MuJoCo scene and its forward kinematics.

    Build with :meth:`load`; :attr:`bodies` is the static geometry, :meth:`pose` the body poses
    (world frame of the scene) at the given arm joints.
    """

    def __init__(self, spec: RobotSpec, model: Any) -> None:
        import mujoco

        self._mj = mujoco
        self.spec = spec
        self.model = model
        self.data = mujoco.MjData(model)
        self.bodies = self._bodies()
        #: kind → every drawn primitive of that kind, of every body (the order of
        #: :meth:`primitive_poses`)
        self.primitives: dict[str, tuple[Primitive, ...]] = {
            k: ps for k in KINDS if (ps := tuple(p for b in self.bodies for p in b.primitives if p.kind == k))
        }
        #: the bodies with meshes (posed one by one: :meth:`pose`)
        self.mesh_bodies = tuple(b for b in self.bodies if b.meshes)
        self._geoms = {k: np.asarray([p.geom for p in ps], np.int64) for k, ps in self.primitives.items()}
        self._qpos_of: dict[tuple[str, ...], npt.NDArray[np.int64]] = {}

    @classmethod
    def load(cls, spec: RobotSpec) -> RobotGeometry:
        """The geometry of the registered robot ``spec`` from its scene file.

        Raises:
            ConfigError: the scene does not load.
        """
        import mujoco

        try:
            model = mujoco.MjModel.from_xml_path(str(spec.scene))
        except ValueError as exc:
            raise ConfigError(f"robot {spec.name!r}: scene {spec.scene} does not load: {exc}") from exc
        return cls(spec, model)

    def _bodies(self) -> tuple[Body, ...]:
        m, mj = self.model, self._mj
        kinds = {
            int(mj.mjtGeom.mjGEOM_BOX): "box",
            int(mj.mjtGeom.mjGEOM_SPHERE): "ellipsoid",
            int(mj.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
            int(mj.mjtGeom.mjGEOM_CAPSULE): "capsule",
            int(mj.mjtGeom.mjGEOM_CYLINDER): "cylinder",
        }
        mesh_type = int(mj.mjtGeom.mjGEOM_MESH)
        out: list[Body] = []
        for b in range(1, m.nbody):  # 0: the world body (the scene around the robot)
            if int(m.body_mocapid[b]) >= 0:
                continue
            prims: list[Primitive] = []
            meshes: list[MeshPart] = []
            first, n = int(m.body_geomadr[b]), int(m.body_geomnum[b])
            for g in range(first, first + n) if first >= 0 else ():
                rgba = _rgba(m, g)
                if int(m.geom_group[g]) not in VISIBLE_GROUPS or rgba[3] == 0:
                    continue
                t = int(m.geom_type[g])
                size = np.array(m.geom_size[g], np.float64)
                pos = np.array(m.geom_pos[g], np.float64)
                quat = np.array(m.geom_quat[g], np.float64)
                if t in kinds:
                    kind = kinds[t]
                    if kind == "ellipsoid" and t == int(mj.mjtGeom.mjGEOM_SPHERE):
                        size = np.full(3, size[0])
                    elif kind in ("capsule", "cylinder"):
                        size = np.array([size[0], 2.0 * size[1]])
                    prims.append(Primitive(kind, size, pos, quat, rgba, g))
                elif t == mesh_type:
                    mid = int(m.geom_dataid[g])
                    va, vn = int(m.mesh_vertadr[mid]), int(m.mesh_vertnum[mid])
                    fa, fn = int(m.mesh_faceadr[mid]), int(m.mesh_facenum[mid])
                    v = np.array(m.mesh_vert[va : va + vn], np.float64)
                    f = np.array(m.mesh_face[fa : fa + fn], np.uint32)
                    meshes.append(MeshPart(v @ quat_matrix(quat).T + pos, f, rgba))
            if prims or meshes:
                name = mj.mj_id2name(m, mj.mjtObj.mjOBJ_BODY, b) or f"body{b}"
                out.append(Body(name, b, tuple(prims), tuple(meshes)))
        return tuple(out)

    def _qpos_indices(self, profile: ArmProfile) -> npt.NDArray[np.int64]:
        idx = self._qpos_of.get(profile.model_joints)
        if idx is None:
            m, mj = self.model, self._mj
            adr = []
            for name in profile.model_joints:
                j = mj.mj_name2id(m, mj.mjtObj.mjOBJ_JOINT, name)
                if j < 0:
                    raise ConfigError(
                        f"robot {self.spec.name!r}: joint {name!r} of arm {profile.arm!r} "
                        f"is not in {self.spec.scene}"
                    )
                adr.append(int(m.jnt_qposadr[j]))
            idx = self._qpos_of[profile.model_joints] = np.asarray(adr, np.int64)
        return idx

    def pose(
        self, arms: Mapping[str, tuple[ArmProfile, Sequence[float] | FloatArray]]
    ) -> dict[str, tuple[FloatArray, FloatArray]]:
        """Body name → (position (3,) [m], orientation quaternion w x y z (4,)) in the scene's world
        frame, for every drawn body, with each arm's joints (arm id → (profile, q)) set.

        Raises:
            ConfigError: an arm's joint is not in the model.
            ValueError: a ``q`` has the wrong length.
        """
        d = self._kinematics(arms)
        return {b.name: (d.xpos[b.index].copy(), d.xquat[b.index].copy()) for b in self.bodies}

    def primitive_poses(
        self, arms: Mapping[str, tuple[ArmProfile, Sequence[float] | FloatArray]]
    ) -> dict[str, tuple[FloatArray, FloatArray]]:
        """Primitive kind → (centres (N, 3) [m], orientations as quaternions w x y z (N, 4)) in the
        scene's world frame of every primitive of :attr:`primitives` of that kind, in that order,
        with each arm's joints set (as :meth:`pose`; the same errors).
        """
        d = self._kinematics(arms)
        out: dict[str, tuple[FloatArray, FloatArray]] = {}
        for k, g in self._geoms.items():
            quats = np.empty((g.size, 4), np.float64)
            for q, xmat in zip(quats, d.geom_xmat[g], strict=True):
                self._mj.mju_mat2Quat(q, xmat)
            out[k] = (d.geom_xpos[g].copy(), quats)
        return out

    def _kinematics(self, arms: Mapping[str, tuple[ArmProfile, Sequence[float] | FloatArray]]) -> Any:
        d = self.data
        for profile, q in arms.values():
            idx = self._qpos_indices(profile)
            qa = np.asarray(q, np.float64)
            if qa.shape != idx.shape:
                raise ValueError(f"arm {profile.arm!r}: {qa.size} joints, the model has {idx.size}")
            d.qpos[idx] = qa
        self._mj.mj_kinematics(self.model, d)
        return d


def moved(
    last: tuple[FloatArray, FloatArray] | None, now: tuple[FloatArray, FloatArray], eps: float = POSE_EPS
) -> bool:
    """The body pose ``now`` differs from ``last`` (None: never sent) by more than ``eps``."""
    if last is None:
        return True
    dq = min(float(np.abs(last[1] - now[1]).max()), float(np.abs(last[1] + now[1]).max()))
    return float(np.abs(last[0] - now[0]).max()) > eps or dq > eps
