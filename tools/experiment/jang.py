"""Jang 2014's evaluation of Virtual-Incision-Port (VIP) control, in kinematics and in MuJoCo.

Reproduces, with the arm of :mod:`telesurg.shared.robots.vip.kinematics` and the two-arm model
``shared/robots/vip``:

* **Fig. 6** — a reference wrist trajectory (a 20 mm circle around the Table I initial wrist,
  with a ±5 mm depth swing) resolved with the paper's VIP (0.0420, -0.0554, -0.0803) m: the wrist
  computed by forward kinematics of the IK solution against the reference, the elbow trajectory,
  and how far the elbow is from the line V-W (the "virtual instrument").
* **The same trajectory in MuJoCo** — both arms, joint setpoints computed at 25 Hz (every
  40 ms, the paper's master rate), interpolated to 1 kHz by the slave's
  :class:`~telesurg.services.slave_control.control.SetpointInterpolator` into the position servos,
  ``mj_step`` at 1 ms; the wrist site against the reference and the joint-velocity steps.
* **Fig. 9** — a target outside the working area of one VIP (the IK violates Table I) becomes
  reachable after reallocating the VIP with the paper's selection procedure.
* **The central claim** — elbow excursion with VIP control against the pseudo-inverse Jacobian
  resolution (:func:`~telesurg.shared.robots.vip.kinematics.pinv_step`) on the same wrist trajectory.

The paper's VIP in the frame of ``vip.py``
-------------------------------------------
The paper gives the VIP in its "base coordinates": origin at the RCM point R, z1 up (the q1 axis).
:data:`~telesurg.shared.robots.vip.kinematics.VIP_ARM` uses the same origin and z1, but the direction of x1
(the
zero of q1) is a convention the paper never shows, and with the chosen α, β, forearm and Table I
our arm can only put its elbow at azimuths 72°-172° about z1, never at the paper's -52.8°. The
printed VIP is therefore turned about z1 by :data:`VIP_ROTATION_DEG` (the angle that brings it
into the vertical half-plane of the VIP selected by the paper's procedure at the Table I initial
pose); its depth (-0.0803 m), its distance from z1 (0.0695 m) and |RV| = 0.106 m are kept. With
the wrist at the initial pose this VIP gives the joints (21.4°, 32.4°, -0.141 m, 32.1°, 46.6°),
within 2.4° / 1 mm of Table I's initial (20°, 30°, -0.14 m, 30°, 45°): the printed VIP fits the
mid-range start the paper recommends. Each arm of the MuJoCo model then carries it into the world
(port) frame with its base transform (:data:`VIP_ARM1`, :data:`VIP_ARM2`).

Output: ``metrics.json`` and ``jang-fig6.png``, ``jang-fig9.png``, ``jang-elbow.png``,
``jang-sim.png``. Runs in a few seconds.

Example::

    telesurg experiment jang-vip --out /tmp/jang
    python -c "from pathlib import Path; import telesurg.tools.experiment.jang as j; j.run(Path('/tmp/j'))"
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from telesurg.services.slave_control.control import SetpointInterpolator
from telesurg.services.slave_control.models import model_path
from telesurg.shared import jsonio
from telesurg.shared.kinematics.transforms import FloatArray, rot_z
from telesurg.shared.robots.vip.kinematics import (
    EV_DEFAULT,
    EV_MAX,
    EV_MIN,
    VIP_ARM,
    VIP_ARM1,
    VIP_ARM2,
    JointLimitError,
    VipArmGeometry,
    fk,
    ik,
    pinv_step,
    select_vip,
    vip_elbow,
    vip_ik,
    within_limits,
)

__all__ = ["PAPER_VIP_M", "VIP_ROTATION_DEG", "paper_vip", "reference_wrist", "run"]

PAPER_VIP_M = (0.0420, -0.0554, -0.0803)
"""The VIP of the paper's simulation (Fig. 6) [m], in its base coordinates (R at the origin)."""


def _vip_rotation() -> float:
    """Angle [rad] about z1 taking the paper's VIP into the half-plane of ``select_vip(home)``."""
    v_home = select_vip(VIP_ARM.home_q, EV_DEFAULT, VIP_ARM)
    return math.atan2(float(v_home[1]), float(v_home[0])) - math.atan2(PAPER_VIP_M[1], PAPER_VIP_M[0])


VIP_ROTATION_DEG = math.degrees(_vip_rotation())
"""Rotation [deg] about z1 from the paper's base frame to that of ``vip.py`` (148.66°)."""

CIRCLE_RADIUS_M = 0.020
"""Radius [m] of the reference wrist circle (Fig. 6's trajectory is a closed loop of a few cm)."""
DEPTH_SWING_M = 0.005
"""Depth swing [m] of the circle (``± DEPTH_SWING_M · sin 2θ`` along z1): a 3-D loop, q3 works too."""
LAP_S = 4.0
"""Duration [s] of the lap; θ(t) = π(1 - cos(πt/LAP_S)) starts and ends at rest (peak 49 mm/s)."""
HOLD_S = 0.4
"""Time [s] the simulation keeps running after the lap (the interpolator and servos settle)."""
KIN_RATE_HZ = 100.0
"""Sampling [Hz] of the trajectory for Fig. 6 and the VIP / pseudo-inverse comparison."""
PINV_ITERATIONS = 3
"""Pseudo-inverse steps per waypoint (closed-loop resolved rate, so its wrist follows too)."""
SETPOINT_PERIOD_S = 0.040
"""Period [s] of the joint setpoints (Section V-A: the master command every 40 ms, 25 Hz)."""
SIM_LATENCY_MAX_S = 0.010
"""Setpoints arrive 0-10 ms (uniform, seeded) after their stamp: transport latency and jitter."""
SIM_SEED = 2014
SIM_TRACK_TOL_MM = 1.0
"""Wrist tracking error [mm] the MuJoCo run must stay below, the interpolation delay removed."""
FIG9_TARGET_OFFSET_M = (-0.060, 0.0, 0.0)
"""Fig. 9 target: arm 1's initial wrist moved this far [m] in the port frame (toward the feet)."""
FIG9_GRID_M = 0.0025
"""Spacing [m] of the grid on which the working areas of Fig. 9 are mapped."""

ARMS: tuple[tuple[str, VipArmGeometry], ...] = (("arm1", VIP_ARM1), ("arm2", VIP_ARM2))

Progress = Callable[[str, float], None]
BoolArray = npt.NDArray[np.bool_]


# ------------------------------------------------------------------------------------------------
# Trajectory and VIP
# ------------------------------------------------------------------------------------------------


def paper_vip(geom: VipArmGeometry = VIP_ARM) -> FloatArray:
    """The paper's VIP ``(3,)`` [m] for arm ``geom``: turned about z1, then into the world."""
    v_base = rot_z(math.radians(VIP_ROTATION_DEG)) @ np.array(PAPER_VIP_M)
    return np.asarray(geom.base_rotation @ v_base + np.array(geom.base_position), dtype=np.float64)


def _theta(t: FloatArray) -> FloatArray:
    """Phase [rad] along the circle: 0 → 2π over LAP_S with zero speed at both ends."""
    tc = np.clip(t, 0.0, LAP_S)
    return np.asarray(math.pi * (1.0 - np.cos(math.pi * tc / LAP_S)), dtype=np.float64)


def reference_wrist(t: npt.ArrayLike, geom: VipArmGeometry = VIP_ARM) -> FloatArray:
    """Reference wrist ``(N, 3)`` [m] at times ``t`` ``(N,)`` [s], in the world frame of ``geom``.

    In the arm's base frame: the Table I initial wrist plus ``(r cos θ, r sin θ, h sin 2θ)``,
    r = CIRCLE_RADIUS_M, h = DEPTH_SWING_M. Before 0 and after LAP_S it holds its end point.
    """
    th = _theta(np.atleast_1d(np.asarray(t, dtype=np.float64)))
    w0 = fk(VIP_ARM.home_q, VIP_ARM).wrist
    base = w0 + np.column_stack(
        [CIRCLE_RADIUS_M * np.cos(th), CIRCLE_RADIUS_M * np.sin(th), DEPTH_SWING_M * np.sin(2.0 * th)]
    )
    return np.asarray(base @ geom.base_rotation.T + np.array(geom.base_position), dtype=np.float64)


def _off_line(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distances ``(N,)`` of points ``p`` ``(N, 3)`` from the lines through ``a`` ``(N, 3)`` and ``b``."""
    d = b - a
    cross = np.cross(p - a, d)
    return np.asarray(np.linalg.norm(cross, axis=1) / np.linalg.norm(d, axis=1), dtype=np.float64)


# ------------------------------------------------------------------------------------------------
# Fig. 6 and the VIP / pseudo-inverse comparison (kinematics, arm in the paper's base frame)
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Kin:
    """The lap resolved by VIP and by the pseudo-inverse, in the base frame [m]."""

    t: FloatArray  # (N,)
    ref: FloatArray  # (N, 3) reference wrist
    vip: FloatArray  # (3,)
    q_vip: FloatArray  # (N, 5)
    wrist_vip: FloatArray  # (N, 3) FK of q_vip
    elbow_vip: FloatArray  # (N, 3)
    q_pinv: FloatArray  # (N, 5)
    wrist_pinv: FloatArray
    elbow_pinv: FloatArray


def _kinematics() -> _Kin:
    g = VIP_ARM
    t = np.arange(round(LAP_S * KIN_RATE_HZ) + 1) / KIN_RATE_HZ
    ref = reference_wrist(t, g)
    V = paper_vip(g)
    q_vip = np.array([vip_ik(w, V, g) for w in ref])  # Table I enforced (the paper's were not)
    poses = [fk(q, g) for q in q_vip]
    q = q_vip[0].copy()
    q_pinv = [q.copy()]
    for w in ref[1:]:
        for _ in range(PINV_ITERATIONS):
            q = pinv_step(q, w - fk(q, g).wrist, g)
        q_pinv.append(q.copy())
    pinv_poses = [fk(qp, g) for qp in q_pinv]
    return _Kin(
        t=t,
        ref=ref,
        vip=V,
        q_vip=q_vip,
        wrist_vip=np.array([p.wrist for p in poses]),
        elbow_vip=np.array([p.elbow for p in poses]),
        q_pinv=np.array(q_pinv),
        wrist_pinv=np.array([p.wrist for p in pinv_poses]),
        elbow_pinv=np.array([p.elbow for p in pinv_poses]),
    )


def _path_mm(p: FloatArray) -> float:
    return 1000.0 * float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def _kin_metrics(k: _Kin) -> dict[str, Any]:
    g = VIP_ARM
    n = k.t.size
    vv = np.broadcast_to(k.vip, (n, 3))
    e_vip = np.linalg.norm(k.elbow_vip - k.elbow_vip[0], axis=1)
    e_pinv = np.linalg.norm(k.elbow_pinv - k.elbow_pinv[0], axis=1)
    ev0 = float(np.linalg.norm(k.elbow_vip[0] - k.vip))
    return {
        "vip_paper_m": list(PAPER_VIP_M),
        "vip_rotation_deg": VIP_ROTATION_DEG,
        "vip_base_m": k.vip.tolist(),
        "vip_world_m": {arm: paper_vip(geom).tolist() for arm, geom in ARMS},
        "ev_at_start_mm": 1000.0 * ev0,
        "q_vip_at_initial_wrist": _q_readable(vip_ik(fk(g.home_q, g).wrist, k.vip, g)),
        "trajectory": {
            "radius_mm": 1000.0 * CIRCLE_RADIUS_M,
            "depth_swing_mm": 1000.0 * DEPTH_SWING_M,
            "lap_s": LAP_S,
            "peak_speed_mm_s": 1000.0 * CIRCLE_RADIUS_M * math.pi**2 / LAP_S,
            "samples": n,
        },
        "wrist_track_err_max_m": float(np.max(np.linalg.norm(k.wrist_vip - k.ref, axis=1))),
        "vip_collinearity_max_m": float(np.max(_off_line(k.elbow_vip, vv, k.wrist_vip))),
        "vip_joint_range_deg": {
            "min": _q_readable(k.q_vip.min(axis=0)),
            "max": _q_readable(k.q_vip.max(axis=0)),
        },
        "wrist_path_mm": _path_mm(k.ref),
        "elbow_path_vip_mm": _path_mm(k.elbow_vip),
        "elbow_path_pinv_mm": _path_mm(k.elbow_pinv),
        "elbow_excursion_vip_mm": 1000.0 * float(e_vip.max()),
        "elbow_excursion_pinv_mm": 1000.0 * float(e_pinv.max()),
        "elbow_off_line_vip_mm": 1000.0 * float(np.max(_off_line(k.elbow_vip, vv, k.wrist_vip))),
        "elbow_off_line_pinv_mm": 1000.0 * float(np.max(_off_line(k.elbow_pinv, vv, k.wrist_pinv))),
        "elbow_return_vip_mm": 1000.0 * float(e_vip[-1]),
        "elbow_return_pinv_mm": 1000.0 * float(e_pinv[-1]),
        "pinv_wrist_err_max_mm": 1000.0 * float(np.max(np.linalg.norm(k.wrist_pinv - k.ref, axis=1))),
        "pinv_within_limits": bool(all(within_limits(q, g, 1e-9) for q in k.q_pinv)),
    }


def _q_readable(q: FloatArray) -> list[float]:
    """Joints as [deg, deg, m, deg, deg] (rounded for metrics.json)."""
    return [round(math.degrees(v), 3) if i != 2 else round(v, 5) for i, v in enumerate(q.tolist())]


# ------------------------------------------------------------------------------------------------
# Fig. 9: reallocation of the VIP (arm 1, world / port frame)
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Fig9:
    target: FloatArray
    vip_before: FloatArray
    vip_after: FloatArray
    q_before: FloatArray  # (5,) VIP IK at the target (outside Table I)
    q_home: FloatArray  # (5,) the start configuration (VIP IK at the initial wrist)
    q_after: FloatArray  # (5,) the configuration of the reallocation (= VIP IK at the target after)
    xs: FloatArray
    ys: FloatArray
    area_before: BoolArray
    area_after: BoolArray
    circle: FloatArray  # (N, 3) the Fig. 6 loop in the world


def _max_margin_configuration(target: FloatArray, geom: VipArmGeometry) -> FloatArray:
    """Joints with the wrist at ``target`` and every joint as far inside Table I as possible.

    The paper's Step 2 ("adjust manually elbow and wrist") with Section V-B's advice (joints in
    the middle of their ranges): the elbow is searched on the sphere of forearm radius around
    ``target`` (6° grid, then 1° around its best); the margin is the smallest distance to a
    limit, as a fraction of the joint's range.
    """
    lo, hi = geom.lower_limits, geom.upper_limits
    best, best_q, best_dir = -math.inf, None, (0.0, 0.0)

    def search(thetas: FloatArray, phis: FloatArray) -> None:
        nonlocal best, best_q, best_dir
        for th in thetas.tolist():
            for ph in phis.tolist():
                u = np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])
                try:
                    q = ik(target + geom.forearm * u, target, geom, enforce_limits=False)
                except Exception:  # outside the RCM cone: not a configuration
                    continue
                margin = float(np.min(np.minimum(q - lo, hi - q) / (hi - lo)))
                if margin > best:
                    best, best_q, best_dir = margin, q, (th, ph)

    search(np.radians(np.arange(3.0, 180.0, 6.0)), np.radians(np.arange(-180.0, 180.0, 6.0)))
    th0, ph0 = best_dir
    fine = np.radians(np.arange(-6.0, 6.01, 1.0))
    search(th0 + fine, ph0 + fine)  # 1° around the best direction of the 6° grid
    if best_q is None or best < 0.0:
        raise RuntimeError(f"no configuration within Table I puts the wrist at {target.tolist()}")
    return best_q


def _area(V: FloatArray, xs: FloatArray, ys: FloatArray, z: float, geom: VipArmGeometry) -> BoolArray:
    """``(len(ys), len(xs))`` True where VIP IK of the wrist (x, y, z) is within Table I."""
    out = np.zeros((ys.size, xs.size), dtype=bool)
    for i, y in enumerate(ys.tolist()):
        for j, x in enumerate(xs.tolist()):
            try:
                vip_ik(np.array([x, y, z]), V, geom)
            except JointLimitError:
                continue
            except Exception:  # W on V or outside the RCM cone
                continue
            out[i, j] = True
    return out


def _fig9() -> tuple[_Fig9, dict[str, Any]]:
    g = VIP_ARM1
    w0 = fk(g.home_q, g).wrist
    target = w0 + np.array(FIG9_TARGET_OFFSET_M)
    V_a = paper_vip(g)
    q_home = vip_ik(w0, V_a, g)
    before: dict[str, Any] = {"reachable": True, "violations": []}
    q_before = vip_ik(target, V_a, g, enforce_limits=False)
    try:
        vip_ik(target, V_a, g)
    except JointLimitError as exc:
        before = {
            "reachable": False,
            "error": str(exc),
            "violations": [
                {
                    "joint": v.joint,
                    "value": _unit(v.joint_index, v.value),
                    "limit": _unit(v.joint_index, v.limit),
                    "excess": _unit(v.joint_index, v.excess),
                    "unit": "m" if v.joint_index == 2 else "deg",
                }
                for v in exc.violations
            ],
        }
    # Only |EV| changed: V slides along the virtual instrument of the start pose.
    ev_only: dict[str, bool] = {}
    e0 = vip_elbow(w0, V_a, g)
    for ev in (EV_MIN, 0.5 * (EV_MIN + EV_MAX), EV_MAX):
        V = e0 + (e0 - w0) / np.linalg.norm(e0 - w0) * ev
        try:
            vip_ik(target, V, g)
            ev_only[f"{1000.0 * ev:.0f}"] = True
        except JointLimitError:
            ev_only[f"{1000.0 * ev:.0f}"] = False
    # Reallocation (Steps 2-6): instrument moved to the new site, V selected from its joints.
    q_after = _max_margin_configuration(target, g)
    V_b = select_vip(q_after, EV_DEFAULT, g)
    after: dict[str, Any]
    try:
        q_check = vip_ik(target, V_b, g)
        after = {
            "reachable": True,
            "q": _q_readable(q_check),
            "wrist_err_m": float(np.linalg.norm(fk(q_check, g).wrist - target)),
        }
    except JointLimitError as exc:
        q_check = q_after
        after = {"reachable": False, "error": str(exc)}
    xs = np.arange(-0.11, 0.05 + 1e-9, FIG9_GRID_M)
    ys = np.arange(-0.13, 0.03 + 1e-9, FIG9_GRID_M)
    z = float(target[2])
    area_a = _area(V_a, xs, ys, z, g)
    area_b = _area(V_b, xs, ys, z, g)
    cell_cm2 = (100.0 * FIG9_GRID_M) ** 2
    res = _Fig9(
        target=target,
        vip_before=V_a,
        vip_after=V_b,
        q_before=q_before,
        q_home=q_home,
        q_after=q_check,
        xs=xs,
        ys=ys,
        area_before=area_a,
        area_after=area_b,
        circle=reference_wrist(np.linspace(0.0, LAP_S, 201), g),
    )
    metrics: dict[str, Any] = {
        "reallocation_made_reachable": bool(not before["reachable"] and after["reachable"]),
        "reallocation": {
            "arm": "arm1",
            "frame": "world (port frame)",
            "target_m": target.tolist(),
            "target_offset_from_initial_wrist_m": list(FIG9_TARGET_OFFSET_M),
            "vip_before_m": V_a.tolist(),
            "vip_after_m": V_b.tolist(),
            "vip_moved_mm": 1000.0 * float(np.linalg.norm(V_b - V_a)),
            "ev_after_mm": 1000.0 * EV_DEFAULT,
            "before": before,
            "ev_only_reachable": ev_only,
            "reallocated_at_q": _q_readable(q_after),
            "after": after,
            "working_area_depth_m": z,
            "working_area_before_cm2": cell_cm2 * int(area_a.sum()),
            "working_area_after_cm2": cell_cm2 * int(area_b.sum()),
        },
    }
    return res, metrics


def _unit(index: int, x: float) -> float:
    return round(x, 5) if index == 2 else round(math.degrees(x), 3)


# ------------------------------------------------------------------------------------------------
# MuJoCo: 25 Hz setpoints → SetpointInterpolator at 1 kHz → position servos
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _SimArm:
    name: str
    t: FloatArray  # (N,) time after each step [s]
    wrist: FloatArray  # (N, 3) MuJoCo wrist site
    elbow: FloatArray  # (N, 3)
    ctrl: FloatArray  # (N, 5) interpolated reference sent to the servos during each step
    qvel: FloatArray  # (N, 5) MuJoCo joint velocities after each step
    t_sp: FloatArray  # (K,) setpoint times
    q_sp: FloatArray  # (K, 5) setpoints
    delay: float  # s, source time → reference played by the interpolator
    buffer_delay: float  # s, the interpolator's jitter-buffer delay
    vip: FloatArray  # (3,)
    geom: VipArmGeometry


def _simulate() -> tuple[list[_SimArm], int]:
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(model_path("vip")))
    d = mujoco.MjData(m)
    dt = float(m.opt.timestep)
    n_steps = round((LAP_S + HOLD_S) / dt)
    n_sp = round((LAP_S + HOLD_S) / SETPOINT_PERIOD_S) + 1
    t_sp = np.asarray(np.arange(n_sp) * SETPOINT_PERIOD_S, dtype=np.float64)
    rng = np.random.default_rng(SIM_SEED)
    q_sp, vips, interps, arrivals = [], [], [], []
    # each arm's five joints in qpos / qvel (its jaw fingers follow them: not 5 j … 5 j + 5)
    joints = [[m.joint(f"{arm}_q{i}").id for i in range(1, 6)] for arm, _ in ARMS]
    qadr = [m.jnt_qposadr[js] for js in joints]
    dadr = [m.jnt_dofadr[js] for js in joints]
    for j, (_, geom) in enumerate(ARMS):
        V = paper_vip(geom)
        q = np.array([vip_ik(w, V, geom) for w in reference_wrist(t_sp, geom)])
        q_sp.append(q)
        vips.append(V)
        interps.append(SetpointInterpolator())
        arrivals.append(t_sp + rng.uniform(0.0, SIM_LATENCY_MAX_S, n_sp))
        d.qpos[qadr[j]] = q[0]
        d.ctrl[5 * j : 5 * j + 5] = q[0]
    mujoco.mj_forward(m, d)
    sites = [(m.site(f"{arm}_wrist").id, m.site(f"{arm}_elbow").id) for arm, _ in ARMS]
    t_out = np.empty(n_steps)
    wrist = np.empty((len(ARMS), n_steps, 3))
    elbow = np.empty((len(ARMS), n_steps, 3))
    ctrl = np.empty((n_steps, m.nu))
    qvel = np.empty((n_steps, m.nv))
    pushed = [0] * len(ARMS)
    for n in range(n_steps):
        now = n * dt
        for j, interp in enumerate(interps):
            # The slave's cycle: every setpoint that arrived since the last cycle, then sample.
            while pushed[j] < n_sp and arrivals[j][pushed[j]] <= now:
                k = pushed[j]
                interp.push(q_sp[j][k], float(t_sp[k]), float(arrivals[j][k]))
                pushed[j] += 1
            ref = interp.sample(now)
            if ref is not None:
                d.ctrl[5 * j : 5 * j + 5] = ref
        ctrl[n] = d.ctrl
        mujoco.mj_step(m, d)
        t_out[n] = d.time
        qvel[n] = d.qvel
        for j, (w_id, e_id) in enumerate(sites):
            wrist[j, n] = d.site_xpos[w_id]
            elbow[j, n] = d.site_xpos[e_id]
    warnings = int(sum(int(w.number) for w in d.warning))
    arms = [
        _SimArm(
            name=arm,
            t=t_out,
            wrist=wrist[j],
            elbow=elbow[j],
            ctrl=ctrl[:, 5 * j : 5 * j + 5],
            qvel=qvel[:, dadr[j]],
            t_sp=t_sp,
            q_sp=q_sp[j],
            # The playback runs the source timeline at (arrival - stamp of the second setpoint)
            # + the buffer delay (1.5 setpoint periods) behind.
            delay=float(arrivals[j][1] - t_sp[1]) + interps[j].delay,
            buffer_delay=interps[j].delay,
            vip=vips[j],
            geom=geom,
        )
        for j, (arm, geom) in enumerate(ARMS)
    ]
    return arms, warnings


_REVOLUTE = np.array([0, 1, 3, 4])  # q3 (index 2) is prismatic: its velocities are in m/s


def _errors_mm(a: _SimArm, delay: float) -> FloatArray:
    ref = reference_wrist(a.t - delay, a.geom)
    return np.asarray(1000.0 * np.linalg.norm(a.wrist - ref, axis=1), dtype=np.float64)


def _sim_arm_metrics(a: _SimArm) -> dict[str, Any]:
    dt = float(a.t[1] - a.t[0])
    err = _errors_mm(a, a.delay)
    raw = _errors_mm(a, 0.0)
    delays = np.arange(0.0, 0.0801, 0.0005)
    rms = [float(np.sqrt(np.mean(_errors_mm(a, float(dl)) ** 2))) for dl in delays]
    best = int(np.argmin(rms))
    v_cmd = np.diff(a.ctrl, axis=0) / dt  # velocity of the reference in each 1 ms cycle
    step_cmd = np.abs(np.diff(v_cmd, axis=0))
    step_meas = np.abs(np.diff(a.qvel, axis=0))
    # What linear interpolation allows: at each setpoint the speed changes from one setpoint
    # increment per period to the next (rest before the first and after the last setpoint).
    q = np.vstack([a.q_sp[:1], a.q_sp, a.q_sp[-1:]])
    bound = np.abs(np.diff(q, n=2, axis=0)) / SETPOINT_PERIOD_S
    zoh = np.abs(np.diff(a.q_sp, axis=0)) / dt  # setpoints applied as they come, in one cycle
    vv = np.broadcast_to(a.vip, a.elbow.shape)
    return {
        "delay_ms": 1000.0 * a.delay,
        "buffer_delay_ms": 1000.0 * a.buffer_delay,
        "wrist_track_err_max_mm": float(err.max()),
        "wrist_track_err_rms_mm": float(np.sqrt(np.mean(err**2))),
        "wrist_track_err_raw_max_mm": float(raw.max()),
        "wrist_track_err_raw_rms_mm": float(np.sqrt(np.mean(raw**2))),
        "effective_delay_ms": 1000.0 * float(delays[best]),
        "wrist_track_err_rms_mm_at_effective_delay": rms[best],
        "wrist_err_final_mm": float(err[-1]),
        "elbow_off_line_max_mm": 1000.0 * float(np.max(_off_line(a.elbow, vv, a.wrist))),
        "joint_vel_step_max_rad_s": float(step_cmd[:, _REVOLUTE].max()),
        "joint_vel_step_bound_rad_s": float(bound[:, _REVOLUTE].max()),
        "joint_vel_step_zoh_rad_s": float(zoh[:, _REVOLUTE].max()),
        "joint_vel_step_measured_max_rad_s": float(step_meas[:, _REVOLUTE].max()),
        "joint_vel_max_rad_s": float(np.abs(v_cmd[:, _REVOLUTE]).max()),
        "q3_vel_step_max_m_s": float(step_cmd[:, 2].max()),
        "q3_vel_step_bound_m_s": float(bound[:, 2].max()),
        "setpoints": int(a.t_sp.size),
        "steps": int(a.t.size),
    }


def _sim_metrics(arms: list[_SimArm], warnings: int) -> dict[str, Any]:
    per = {a.name: _sim_arm_metrics(a) for a in arms}

    def worst(key: str) -> float:
        return max(float(p[key]) for p in per.values())

    return {
        "wrist_track_err_max_mm_sim": worst("wrist_track_err_max_mm"),
        "wrist_track_err_rms_mm_sim": worst("wrist_track_err_rms_mm"),
        "wrist_track_err_raw_max_mm_sim": worst("wrist_track_err_raw_max_mm"),
        "wrist_track_err_raw_rms_mm_sim": worst("wrist_track_err_raw_rms_mm"),
        "elbow_off_line_max_mm_sim": worst("elbow_off_line_max_mm"),
        "joint_vel_step_max_rad_s": worst("joint_vel_step_max_rad_s"),
        "joint_vel_step_bound_rad_s": worst("joint_vel_step_bound_rad_s"),
        "joint_vel_step_zoh_rad_s": worst("joint_vel_step_zoh_rad_s"),
        "joint_vel_step_measured_max_rad_s": worst("joint_vel_step_measured_max_rad_s"),
        "sim_track_tol_mm": SIM_TRACK_TOL_MM,
        "sim_delay_compensated_ms": {a.name: 1000.0 * a.delay for a in arms},
        "sim_latency_max_ms": 1000.0 * SIM_LATENCY_MAX_S,
        "sim_setpoint_rate_hz": 1.0 / SETPOINT_PERIOD_S,
        "sim_mujoco_warnings": warnings,
        "sim": per,
    }


# ------------------------------------------------------------------------------------------------
# Figures
# ------------------------------------------------------------------------------------------------


def _figures(out: Path, kin: _Kin, f9: _Fig9, f9m: dict[str, Any], sim: list[_SimArm]) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths: list[Path] = []
    mm = 1000.0

    # Fig. 6 --------------------------------------------------------------------------------
    fig = plt.figure(figsize=(15, 5), layout="constrained")
    ax3: Any = fig.add_subplot(1, 3, 1, projection="3d")
    ref, wr, el, V = mm * kin.ref, mm * kin.wrist_vip, mm * kin.elbow_vip, mm * kin.vip
    ax3.plot(ref[:, 0], ref[:, 1], ref[:, 2], "k-", lw=3, alpha=0.35, label="reference wrist")
    ax3.plot(wr[:, 0], wr[:, 1], wr[:, 2], "k--", lw=1, label="computed wrist (FK of IK)")
    ax3.plot(el[:, 0], el[:, 1], el[:, 2], "b-", lw=1.5, label="computed elbow")
    ax3.scatter([V[0]], [V[1]], [V[2]], color="r", marker="x", s=60, label="VIP")
    ax3.scatter([0.0], [0.0], [0.0], color="k", marker="o", s=20, label="R (RCM)")
    for i in range(0, kin.t.size - 1, kin.t.size // 8):
        line = np.vstack([V, wr[i]])
        ax3.plot(line[:, 0], line[:, 1], line[:, 2], "g-", lw=0.6, alpha=0.6)
        shaft = np.vstack([[0.0, 0.0, 0.0], el[i]])
        ax3.plot(shaft[:, 0], shaft[:, 1], shaft[:, 2], color="0.5", lw=0.6)
    ax3.set_xlabel("x [mm]")
    ax3.set_ylabel("y [mm]")
    ax3.set_zlabel("z [mm]")
    ax3.legend(fontsize=7, loc="upper left")
    ax3.set_title("base frame (R = origin); green: virtual instrument V-W", fontsize=9)
    for ax, (i, j) in zip(
        (fig.add_subplot(1, 3, 2), fig.add_subplot(1, 3, 3)), ((0, 1), (0, 2)), strict=True
    ):
        ax.plot(ref[:, i], ref[:, j], "k-", lw=3, alpha=0.35, label="reference wrist")
        ax.plot(wr[:, i], wr[:, j], "k--", lw=1, label="computed wrist")
        ax.plot(el[:, i], el[:, j], "b-", lw=1.5, label="computed elbow")
        ax.plot([V[i]], [V[j]], "rx", ms=8, label="VIP")
        ax.set_xlabel(f"{'xyz'[i]} [mm]")
        ax.set_ylabel(f"{'xyz'[j]} [mm]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
    err = np.linalg.norm(kin.wrist_vip - kin.ref, axis=1).max()
    fig.axes[1].set_title(f"top view; max |W_FK - W_ref| = {err:.1e} m", fontsize=9)
    fig.axes[2].set_title("side view (x-z)", fontsize=9)
    fig.axes[1].legend(fontsize=7)
    fig.suptitle(
        f"Fig. 6: wrist and elbow from VIP IK, VIP = paper's {PAPER_VIP_M} m turned "
        f"{VIP_ROTATION_DEG:.1f}° about z1 = ({V[0]:.1f}, {V[1]:.1f}, {V[2]:.1f}) mm"
    )
    paths.append(out / "jang-fig6.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # Fig. 9 --------------------------------------------------------------------------------
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.6), layout="constrained")
    extent = (mm * (f9.xs[0] - 0.5 * FIG9_GRID_M), mm * (f9.xs[-1] + 0.5 * FIG9_GRID_M))
    extent_y = (mm * (f9.ys[0] - 0.5 * FIG9_GRID_M), mm * (f9.ys[-1] + 0.5 * FIG9_GRID_M))
    g = VIP_ARM1
    realloc = f9m["reallocation"]
    panels = (
        (axes[0], f9.area_before, f9.vip_before, f9.q_home, "C0", "(a) VIP of Fig. 6: target unreachable"),
        (axes[1], f9.area_after, f9.vip_after, f9.q_after, "C1", "(b) VIP reallocated: target reached"),
    )
    for ax, area, V9, q, color, title in panels:
        ax.imshow(
            np.where(area, 1.0, np.nan),
            origin="lower",
            extent=(*extent, *extent_y),
            cmap="Blues" if color == "C0" else "Oranges",
            vmin=0.0,
            vmax=1.6,
            alpha=0.8,
        )
        loop = mm * f9.circle
        ax.plot(loop[:, 0], loop[:, 1], "k-", lw=1, label="Fig. 6 wrist loop (start site)")
        p = fk(q, g)
        arm = mm * np.vstack([p.rcm, p.elbow, p.wrist])
        ax.plot(arm[:, 0], arm[:, 1], "-o", color="0.3", ms=3, lw=1.5, label="arm R-E-W (top view)")
        vw = mm * np.vstack([V9, p.wrist])
        ax.plot(vw[:, 0], vw[:, 1], "g-", lw=1, label="virtual instrument V-W")
        ax.plot([mm * V9[0]], [mm * V9[1]], "x", color="r", ms=9, mew=2, label="VIP")
        ok = area is f9.area_after and realloc["after"]["reachable"]
        ax.plot(
            [mm * f9.target[0]],
            [mm * f9.target[1]],
            "*",
            color="g" if ok else "r",
            ms=14,
            label="target (reached)" if ok else "target (IK outside Table I)",
        )
        ax.set_xlabel("x [mm] (toward the head)")
        ax.set_ylabel("y [mm] (toward the patient's left)")
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7, loc="upper right")
    pb = fk(f9.q_before, g)
    arm_b = mm * np.vstack([pb.rcm, pb.elbow, pb.wrist])
    axes[0].plot(
        arm_b[:, 0], arm_b[:, 1], "--o", color="r", ms=3, lw=1, label="arm at the target (outside Table I)"
    )
    axes[0].legend(fontsize=7, loc="upper right")
    before = realloc["before"]
    viol = ", ".join(f"{v['joint']} over by {v['excess']:.1f}°" for v in before["violations"])
    axes[0].text(
        0.02, 0.02, f"target: {viol}", transform=axes[0].transAxes, fontsize=8, va="bottom", color="r"
    )
    axes[1].text(
        0.02,
        0.02,
        f"VIP moved {realloc['vip_moved_mm']:.0f} mm; areas {realloc['working_area_before_cm2']:.1f} → "
        f"{realloc['working_area_after_cm2']:.1f} cm²",
        transform=axes[1].transAxes,
        fontsize=8,
        va="bottom",
    )
    fig.suptitle(
        f"Fig. 9: working area of arm 1 at depth z = {mm * f9.target[2]:.0f} mm (port frame), "
        "where VIP IK stays within Table I"
    )
    paths.append(out / "jang-fig9.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # Elbow: VIP vs pseudo-inverse ------------------------------------------------------------
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.8), layout="constrained")
    ep = mm * kin.elbow_pinv
    ax = axes[0]
    ax.plot(ref[:, 0], ref[:, 1], "k-", lw=2.5, alpha=0.35, label="wrist (both)")
    ax.plot(el[:, 0], el[:, 1], "b-", lw=1.5, label="elbow, VIP")
    ax.plot(ep[:, 0], ep[:, 1], "r-", lw=1.5, label="elbow, pseudo-inverse")
    ax.plot([el[0, 0]], [el[0, 1]], "ko", ms=4, label="elbow start")
    ax.plot([V[0]], [V[1]], "rx", ms=8, label="VIP")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("top view, base frame", fontsize=9)
    vv = np.broadcast_to(kin.vip, kin.elbow_vip.shape)
    for series, label, axis in (
        (
            (
                np.linalg.norm(kin.elbow_vip - kin.elbow_vip[0], axis=1),
                np.linalg.norm(kin.elbow_pinv - kin.elbow_pinv[0], axis=1),
            ),
            "elbow distance from its start [mm]",
            axes[1],
        ),
        (
            (_off_line(kin.elbow_vip, vv, kin.wrist_vip), _off_line(kin.elbow_pinv, vv, kin.wrist_pinv)),
            "elbow distance from the line V-W [mm]",
            axes[2],
        ),
    ):
        axis.plot(kin.t, mm * series[0], "b-", label=f"VIP (max {mm * series[0].max():.2f} mm)")
        axis.plot(kin.t, mm * series[1], "r-", label=f"pseudo-inverse (max {mm * series[1].max():.2f} mm)")
        axis.set_xlabel("t [s]")
        axis.set_ylabel(label)
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=8)
    fig.suptitle("Same wrist loop: elbow under VIP control vs pseudo-inverse Jacobian (minimum joint norm)")
    paths.append(out / "jang-elbow.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    # MuJoCo ------------------------------------------------------------------------------------
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8), layout="constrained")
    for a, style in zip(sim, ("-", "--"), strict=True):
        axes[0].plot(a.t, _errors_mm(a, 0.0), "C3" + style, lw=1, label=f"{a.name}: vs reference at t")
        axes[0].plot(
            a.t,
            _errors_mm(a, a.delay),
            "C0" + style,
            lw=1,
            label=f"{a.name}: vs reference at t - {1000 * a.delay:.1f} ms (playback delay)",
        )
    axes[0].axhline(SIM_TRACK_TOL_MM, color="k", lw=0.8, ls=":", label="tolerance (delay removed)")
    axes[0].set_xlabel("t [s]")
    axes[0].set_ylabel("|W_MuJoCo - W_ref| [mm]")
    axes[0].grid(True, alpha=0.3)
    axes[0].legend(fontsize=7)
    axes[0].set_title("wrist tracking error (25 Hz setpoints, 1 kHz interpolation)", fontsize=9)
    a = sim[0]
    dt = float(a.t[1] - a.t[0])
    v_cmd = np.diff(a.ctrl, axis=0) / dt
    for ax, window in ((axes[1], (0.0, float(a.t[-1]))), (axes[2], (1.6, 2.0))):
        sel = (a.t[1:] >= window[0]) & (a.t[1:] <= window[1])
        for c, jj in enumerate(_REVOLUTE.tolist()):
            ax.plot(a.t[1:][sel] - dt, v_cmd[sel, jj], f"C{c}-", lw=1, label=f"q{jj + 1} reference")
            ax.plot(a.t[1:][sel], a.qvel[1:][sel, jj], f"C{c}:", lw=1.2, label=f"q{jj + 1} MuJoCo")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("joint velocity [rad/s]")
        ax.grid(True, alpha=0.3)
    played = a.t_sp + a.delay
    for t_k in played[(played >= 1.6) & (played <= 2.0)]:
        axes[2].axvline(float(t_k), color="0.8", lw=0.6)
    axes[1].legend(fontsize=7, ncol=2)
    axes[1].set_title("arm1 joint velocities: interpolated reference (solid), MuJoCo (dotted)", fontsize=9)
    axes[2].set_title(
        f"zoom; grey: setpoints as played back (stamp + {1000 * a.delay:.1f} ms, every 40 ms)", fontsize=9
    )
    fig.suptitle("MuJoCo: the Fig. 6 loop on both arms from 25 Hz VIP setpoints")
    paths.append(out / "jang-sim.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


# ------------------------------------------------------------------------------------------------


def run(out: Path, progress: Progress | None = None) -> dict[str, Any]:
    """Reproduce Figs. 6 and 9 and the VIP / pseudo-inverse comparison; run the loop in MuJoCo.

    Args:
        out: output directory (created if missing).
        progress: optional ``progress(stage, fraction)`` callback, fraction in [0, 1].

    Returns:
        The metrics written to ``out/metrics.json`` (lengths in mm unless the key ends in ``_m``,
        angles in degrees, joint velocities in rad/s). Main keys: ``wrist_track_err_max_m`` and
        ``vip_collinearity_max_m`` (Fig. 6, kinematic), ``elbow_excursion_vip_mm`` /
        ``elbow_excursion_pinv_mm`` (largest elbow distance from its start) with
        ``elbow_off_line_*_mm`` and ``elbow_return_*_mm``, ``reallocation_made_reachable`` and
        ``reallocation`` (Fig. 9), ``wrist_track_err_{max,rms}_mm_sim`` (MuJoCo wrist vs the
        reference delayed by the interpolator's playback delay, worst arm),
        ``wrist_track_err_raw_*_mm_sim`` (not delayed), ``joint_vel_step_max_rad_s`` (largest
        change of the 1 kHz joint reference's velocity between two cycles) with
        ``joint_vel_step_bound_rad_s`` (what linear interpolation of the setpoints allows) and
        ``joint_vel_step_zoh_rad_s`` (the same without interpolation), ``sim`` (per arm) and
        ``figures``.
    """

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    out.mkdir(parents=True, exist_ok=True)
    metrics: dict[str, Any] = {}
    report("Fig. 6 and the elbow: VIP vs pseudo-inverse", 0.0)
    kin = _kinematics()
    metrics.update(_kin_metrics(kin))
    report("Fig. 9: reallocation of the VIP", 0.2)
    f9, f9m = _fig9()
    metrics.update(f9m)
    report("MuJoCo, 25 Hz setpoints, 1 kHz interpolation", 0.4)
    sim, warnings = _simulate()
    metrics.update(_sim_metrics(sim, warnings))
    report("figures", 0.75)
    paths = _figures(out, kin, f9, f9m, sim)
    metrics["figures"] = [p.name for p in paths]
    (out / "metrics.json").write_text(jsonio.dumps(metrics, indent=2, sort_keys=True) + "\n")
    report("done", 1.0)
    return metrics
