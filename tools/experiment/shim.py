"""Shim 2015, Section 4, reproduced kinematically: Table-6 mapping vs master tip (no bus, no sim).

Runs the reconstructed PLAS slave and ergonomic master of :mod:`telesurg.shared.robots.plas.kinematics`
through the experiments of the thesis's Section 4 and writes ``metrics.json`` and three PNGs:

* ``shim-joints.png`` — Figs. 20-22: master joint 2, 3 or 4 turned 0→30° alone.
* ``shim-theta3.png`` — Figs. 23-24: master joint 2 turned 0→30° with θ3 = 30° and 60°.
* ``shim-fig26.png`` — Fig. 26: an arbitrary motion of the four master revolute joints.

Every case runs in both mapping modes: ``factor`` (Table 6) and ``tip_exact`` (damped least
squares on the slave Jacobian). Trajectories are compared start-aligned: the *trajectory
error* at time t is ``|(p_s(t) - p_s(0)) - (p_m(t) - p_m(0))|`` in the arm frame, i.e. how far
the slave tip is from where the master's motion would put it. The *path difference* is
``slave path length - master path length``, the yardstick under which the thesis calls the
single-joint cases error-free ("both tips moved 103.6 mm at the same time").

Example::

    telesurg experiment shim-mapping --out /tmp/shim
    python -c "from pathlib import Path; import telesurg.tools.experiment.shim as s; s.run(Path('/tmp/s'))"
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from telesurg.shared import jsonio
from telesurg.shared.kinematics.transforms import FloatArray
from telesurg.shared.robots.plas.kinematics import (
    MappingConfig,
    MappingMode,
    eq29_vx_error,
    follow,
    master_tip_arm,
    slave_tip_arm,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["FIG26_AMPLITUDES_DEG", "SWEEP_DEG", "THESIS", "run"]

SWEEP_DEG = 30.0
"""Master sweep [deg] of every single-joint case (Section 4: "rotated from 0 to 30 degrees")."""

SWEEP_STEPS = 300
"""Steps per sweep (0.1° each); the factor mode's result does not depend on it (midpoint rule)."""

THETA3_CASES_DEG = (30.0, 60.0)
"""θ3 [deg] of both arms in the Figs. 23-24 cases (eq. 29 assumes the arms share their angles)."""

TRACK_TOL_MM = 0.1
"""Trajectory error [mm] below which tip_exact counts as still tracking the master."""

FIG26_SECONDS = 10.0
FIG26_RATE_HZ = 100.0
FIG26_AMPLITUDES_DEG = (15.0, 20.0, 25.0, 40.0)
"""Amplitudes [deg] of master θ2, θ3, θ4, θ5 in the Fig. 26 motion (the thesis's is arbitrary)."""
FIG26_FREQUENCIES_HZ = (0.10, 0.17, 0.13, 0.07)
"""Frequencies [Hz] of the same sines; incommensurate, so the tip draws an open 3-D curve."""

THESIS: dict[str, float] = {
    "j2_slave_deg": 62.5,
    "j3_slave_deg": 40.0,
    "j4_slave_deg": 60.0,
    "j2_arc_mm": 103.6,
    "j3_arc_mm": 31.4,
    "j4_arc_mm": 31.4,
    "err_theta3_30_mm": 8.5,
    "err_theta3_60_mm": 4.46,
    "fig26_err_max_mm": 8.0,  # "error about 8 mm" (which statistic is not said)
}
"""The numbers the thesis reports (Section 4), for the comparison in ``metrics.json``."""

Progress = Callable[[str, float], None]


@dataclass(frozen=True)
class _Run:
    """One master trajectory and the slave's answer to it, tips in the arm frame [m]."""

    q_master: FloatArray  # (T, 6)
    q_slave: FloatArray  # (T, 6)
    tip_master: FloatArray  # (T, 3)
    tip_slave: FloatArray  # (T, 3)
    clamped_steps: int

    @property
    def error_mm(self) -> FloatArray:
        """Trajectory error ``(T,)`` [mm] (start-aligned distance between the tips)."""
        d = (self.tip_slave - self.tip_slave[0]) - (self.tip_master - self.tip_master[0])
        return np.asarray(1000.0 * np.linalg.norm(d, axis=1), dtype=np.float64)

    @property
    def path_master_mm(self) -> float:
        """Length [mm] of the master tip's path."""
        return _path_mm(self.tip_master)

    @property
    def path_slave_mm(self) -> float:
        """Length [mm] of the slave tip's path."""
        return _path_mm(self.tip_slave)


def _path_mm(p: FloatArray) -> float:
    return 1000.0 * float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def _simulate(q_master: FloatArray, q_slave0: FloatArray, dt: float, mode: MappingMode) -> _Run:
    res = follow(q_master, q_slave0, dt=dt, config=MappingConfig(mode=mode))
    return _Run(
        q_master=q_master,
        q_slave=res.q,
        tip_master=np.array([master_tip_arm(q) for q in q_master]),
        tip_slave=np.array([slave_tip_arm(q) for q in res.q]),
        clamped_steps=sum(res.clamp_counts.values()),
    )


def _sweep(joint: int, theta3_deg: float = 0.0) -> tuple[FloatArray, FloatArray]:
    """(master trajectory ``(SWEEP_STEPS + 1, 6)``, slave start ``(6,)``): master ``joint`` 0→30°."""
    qm = np.zeros((SWEEP_STEPS + 1, 6))
    qm[:, 2] = math.radians(theta3_deg)
    qm[:, joint] = np.linspace(0.0, math.radians(SWEEP_DEG), SWEEP_STEPS + 1)
    qs0 = np.zeros(6)
    qs0[2] = math.radians(theta3_deg)
    return qm, qs0


def _fig26_master() -> tuple[FloatArray, float]:
    """(master trajectory ``(T, 6)``, dt [s]): sines on θ2, θ3, θ4, θ5, all starting at 0."""
    dt = 1.0 / FIG26_RATE_HZ
    t = np.arange(round(FIG26_SECONDS * FIG26_RATE_HZ) + 1) * dt
    qm = np.zeros((t.size, 6))
    for j, (amp, freq) in enumerate(zip(FIG26_AMPLITUDES_DEG, FIG26_FREQUENCIES_HZ, strict=True), start=1):
        qm[:, j] = math.radians(amp) * np.sin(2.0 * math.pi * freq * t)
    return qm, dt


def _tracks_to_deg(run: _Run, joint: int) -> float:
    """Master angle [deg] of ``joint`` up to which the trajectory error stays below TRACK_TOL_MM."""
    bad = np.flatnonzero(run.error_mm >= TRACK_TOL_MM)
    k = run.q_master.shape[0] - 1 if bad.size == 0 else max(int(bad[0]) - 1, 0)
    return math.degrees(float(run.q_master[k, joint]))


def _plane(ax: Axes, runs: dict[str, _Run], i: int, j: int, title: str) -> None:
    """Start-aligned tip paths [mm] on the arm-frame plane of axes ``i``, ``j``."""
    names = "xyz"
    first = next(iter(runs.values()))
    pm = 1000.0 * (first.tip_master - first.tip_master[0])
    ax.plot(pm[:, i], pm[:, j], "k-", lw=2.5, label="master handle")
    for (label, run), style in zip(runs.items(), ("C3--", "C0-."), strict=False):
        ps = 1000.0 * (run.tip_slave - run.tip_slave[0])
        ax.plot(ps[:, i], ps[:, j], style, lw=1.6, label=f"slave tip ({label})")
    ax.plot([0.0], [0.0], "ko", ms=4)
    ax.set_xlabel(f"Δ{names[i]} [mm]")
    ax.set_ylabel(f"Δ{names[j]} [mm]")
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)


def _figures(
    out: Path,
    joints: dict[int, dict[str, _Run]],
    theta3: dict[float, dict[str, _Run]],
    fig26: dict[str, _Run],
    dt26: float,
) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths: list[Path] = []

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.4), layout="constrained")
    for ax, (joint, runs) in zip(axes, joints.items(), strict=True):
        f = runs["factor"]
        i, j = (0, 2) if joint == 3 else (0, 1)
        _plane(
            ax,
            {"factor": f},
            i,
            j,
            f"master θ{joint + 1} 0→{SWEEP_DEG:.0f}°, slave θ{joint + 1} → "
            f"{math.degrees(f.q_slave[-1, joint]):.1f}°\npaths {f.path_master_mm:.1f} / "
            f"{f.path_slave_mm:.1f} mm, end gap {f.error_mm[-1]:.1f} mm",
        )
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle("Figs. 20-22: one master joint at a time, Table-6 factors (start-aligned tips)")
    paths.append(out / "shim-joints.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(11, 5), layout="constrained")
    for ax, (th3, runs) in zip(axes, theta3.items(), strict=True):
        f, t = runs["factor"], runs["tip_exact"]
        _plane(
            ax,
            runs,
            0,
            1,
            f"θ3 = {th3:.0f}°, master θ2 0→{SWEEP_DEG:.0f}°: error factor {f.error_mm.max():.1f} mm, "
            f"tip_exact {t.error_mm.max():.1f} mm",
        )
    axes[0].legend(fontsize=8, loc="best")
    fig.suptitle("Figs. 23-24: joint 2 with θ3 ≠ 0 (start-aligned tips, arm frame x-y)")
    paths.append(out / "shim-theta3.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), layout="constrained")
    _plane(axes[0], fig26, 0, 1, "top view (arm frame x-y)")
    _plane(axes[1], fig26, 0, 2, "side view (arm frame x-z)")
    axes[0].legend(fontsize=8, loc="best")
    t_s = np.arange(fig26["factor"].error_mm.size) * dt26
    for (label, run), style in zip(fig26.items(), ("C3-", "C0-"), strict=False):
        e = run.error_mm
        rms = math.sqrt(float(np.mean(e**2)))
        axes[2].plot(t_s, e, style, label=f"{label}: max {e.max():.2f}, rms {rms:.2f} mm")
    axes[2].set_xlabel("t [s]")
    axes[2].set_ylabel("trajectory error [mm]")
    axes[2].grid(True, alpha=0.3)
    axes[2].legend(fontsize=8, loc="best")
    fig.suptitle("Fig. 26: arbitrary motion of master θ2, θ3, θ4, θ5")
    paths.append(out / "shim-fig26.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


def run(out: Path, progress: Progress | None = None) -> dict[str, Any]:
    """Reproduce Section 4; write ``out/metrics.json`` and ``out/shim-*.png``; return the metrics.

    Args:
        out: output directory (created if missing).
        progress: optional ``progress(stage, fraction)`` callback, fraction in [0, 1].

    Returns:
        The metrics written to ``metrics.json``: angles in degrees, lengths in mm. Keys:
        ``j{2,3,4}_slave_deg`` (slave angle after the master's 0→30° sweep),
        ``j{2,3,4}_arc_mm`` / ``j{2,3,4}_slave_arc_mm`` (master / slave tip path),
        ``j{2,3,4}_err_mm`` (trajectory error at the end), ``err_theta3_{30,60}_mm`` and
        ``tip_exact_err_theta3_{30,60}_mm`` (maximum trajectory error of Figs. 23-24),
        ``path_diff_theta3_{30,60}_mm`` and ``tip_exact_path_diff_theta3_{30,60}_mm``,
        ``tip_exact_theta3_{30,60}_tracks_to_deg`` (master θ2 up to which tip_exact stays within
        TRACK_TOL_MM), ``tip_exact_theta3_{30,60}_clamped_steps``, ``eq29_theta3_{30,60}_mm_per_rad``
        (eq. 29 at θ2 = 0), ``fig26_err_{max,rms}_mm`` and ``tip_exact_fig26_err_{max,rms}_mm``,
        ``fig26_path_{master,slave}_mm``, ``figures`` (file names) and ``thesis`` (its numbers).
    """

    def report(stage: str, fraction: float) -> None:
        if progress is not None:
            progress(stage, fraction)

    out.mkdir(parents=True, exist_ok=True)
    modes: tuple[MappingMode, ...] = ("factor", "tip_exact")
    metrics: dict[str, Any] = {}

    report("single-joint sweeps (Figs. 20-22)", 0.0)
    joints: dict[int, dict[str, _Run]] = {}
    for joint in (1, 2, 3):
        qm, qs0 = _sweep(joint)
        f = _simulate(qm, qs0, 0.01, "factor")
        joints[joint] = {"factor": f}
        name = f"j{joint + 1}"
        metrics[f"{name}_slave_deg"] = math.degrees(float(f.q_slave[-1, joint]))
        metrics[f"{name}_arc_mm"] = f.path_master_mm
        metrics[f"{name}_slave_arc_mm"] = f.path_slave_mm
        metrics[f"{name}_err_mm"] = float(f.error_mm[-1])

    report("joint 2 with theta3 = 30, 60 deg (Figs. 23-24)", 0.2)
    theta3: dict[float, dict[str, _Run]] = {}
    for th3 in THETA3_CASES_DEG:
        qm, qs0 = _sweep(1, th3)
        runs: dict[str, _Run] = {mode: _simulate(qm, qs0, 0.01, mode) for mode in modes}
        theta3[th3] = runs
        tag = f"theta3_{th3:.0f}"
        for mode, r in runs.items():
            prefix = "" if mode == "factor" else "tip_exact_"
            metrics[f"{prefix}err_{tag}_mm"] = float(r.error_mm.max())
            metrics[f"{prefix}path_diff_{tag}_mm"] = r.path_slave_mm - r.path_master_mm
        metrics[f"tip_exact_{tag}_tracks_to_deg"] = _tracks_to_deg(runs["tip_exact"], 1)
        metrics[f"tip_exact_{tag}_clamped_steps"] = runs["tip_exact"].clamped_steps
        metrics[f"eq29_{tag}_mm_per_rad"] = 1000.0 * eq29_vx_error(0.0, math.radians(th3))

    report("four-joint motion (Fig. 26)", 0.45)
    qm26, dt26 = _fig26_master()
    fig26: dict[str, _Run] = {mode: _simulate(qm26, np.zeros(6), dt26, mode) for mode in modes}
    for mode, r in fig26.items():
        prefix = "" if mode == "factor" else "tip_exact_"
        e = r.error_mm
        metrics[f"{prefix}fig26_err_max_mm"] = float(e.max())
        metrics[f"{prefix}fig26_err_rms_mm"] = math.sqrt(float(np.mean(e**2)))
    metrics["fig26_path_master_mm"] = fig26["factor"].path_master_mm
    metrics["fig26_path_slave_mm"] = fig26["factor"].path_slave_mm

    report("figures", 0.8)
    paths = _figures(out, joints, theta3, fig26, dt26)
    metrics["figures"] = [p.name for p in paths]
    metrics["thesis"] = dict(THESIS)
    (out / "metrics.json").write_text(jsonio.dumps(metrics, indent=2, sort_keys=True) + "\n")
    report("done", 1.0)
    return metrics
