"""``telesurg bench haptics``: bilateral force feedback under delay, jitter and loss.

Two modes. **In-process** (the default): the simulated Touch and hand
(``services/master_capture/devices/touch_sim``), the haptic loop's force renderer and the bilateral
controllers (``shared/haptics``) run in this process against the real MuJoCo slave model (the MH3F
scene with its touchable tissue, ``MujocoBackend``, the contact wrench slave_control publishes as
``measured_cf``) over a simulated channel: each packet is delayed by half the round trip
× (1 ± jitter), reordered packets are dropped by sequence number, a fraction is lost. Master and
slave run at 1 kHz, the slave's force goes back at 500 Hz (as ``measured_cf``). The slave's tip
follows its target by damped least squares on the arm's Jacobian with a fixed orientation (no
trocar constraint here). It runs all four controllers (none, naive, TDPA, wave), every round trip,
a clean and an impaired channel (56 runs) in minutes; the same device, renderer and controller
code is what the console side runs.

**Through the services** (``--services``, :mod:`telesurg.tools.bench.haptics_services`): one
real local site per run (router, watchdog, slave_control on MuJoCo, mapping; master_capture with
``touch_sim`` and the haptic loop) with the console's link through the userspace link impairer:
delay (half the round trip each way) and, with ``--jitter``, jitter; a TCP proxy loses nothing, so
loss stays the in-process mode's. Controllers none, naive and TDPA (its slave port in the
mapping), the round trips of ``--round-trips-ms``; about 25 s a run.

Per run (one controller, one round trip, one impairment): the tissue's contact force (steady value
while pressing, overshoot = peak / steady), oscillation (RMS of the contact force above 2 Hz while
in contact), the observed energy at each port (the minima of W_m and W_s), the master–slave drift,
the stiffness the master feels vs the tissue's (after the scales), the largest device force, the
free-space master force, and a verdict (``stable``: overshoot ≤ 1.5, no sustained oscillation,
observers ≥ −1 mJ; ``unstable``: overshoot > 3×, a growing oscillation (above 2 Hz: more at the
end of the final hold than at the end of the press, still above 0.05 N rms in its last 0.25 s and
not decaying there), an oscillation above
0.5 N rms, or a network that generated more than 10 mJ — an observer below −10 mJ: the energy the
hand and tissue receive grows beyond what they put in; ``marginal`` otherwise).

The services mode gives the same figures from what the site publishes (module doc of
:mod:`~telesurg.tools.bench.haptics_services`): the observers are W_m (master_capture's) and, for
TDPA, W_s (the mapping's), as each service says at exit; the felt stiffness is not measured there
(the device's force stays inside master_capture).

Example::

    telesurg bench haptics --json docs/data/haptics.json --plot docs/img/haptics.png
    telesurg bench haptics --quick   # 3 round trips, no impairment
    telesurg bench haptics --services --json haptics-services.json --plot haptics-services.png
    telesurg bench haptics --services --quick   # tdpa and naive at 0 and 100 ms
    telesurg bench haptics --diagram docs/img/haptics-architecture.png
"""

from __future__ import annotations

import argparse
import itertools
import json
import random
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.services.master_capture.devices.touch_sim.model import HeldDevice, TouchModel, press_and_slide
from telesurg.services.slave_control.backends import MujocoBackend
from telesurg.shared.haptics import (
    BilateralConfig,
    ForceRenderer,
    MasterPacket,
    RenderConfig,
    SlavePacket,
    make_bilateral,
)
from telesurg.shared.robots import registry

DT = 0.001  # s: master, haptic and slave period
FORCE_EVERY = 2  # slave periods per force packet (500 Hz)
ROUND_TRIPS_MS = (0, 10, 25, 50, 100, 200, 400)
CONTROLLERS = ("none", "naive", "tdpa", "wave")
ABOVE_MM = 20.0  # mm: the slave's anchor above the tissue's contact height
# the script's phases (s): see touch_sim.model.press_and_slide
PRESS, HOLD, SLIDE, END = (1.3, 3.8), (3.3, 3.8), (3.8, 6.3), 7.3


@dataclass
class Channel:
    """One direction of the network: delay × (1 ± jitter), loss, reordering (by arrival time)."""

    one_way_s: float
    jitter: float
    loss: float
    rng: random.Random

    def __post_init__(self) -> None:
        self.queue: list[tuple[float, Any]] = []
        self.cut_at = float("inf")  # s: nothing sent from then on arrives

    def send(self, packet: Any, now: float) -> None:
        if now >= self.cut_at or self.rng.random() < self.loss:
            return
        delay = self.one_way_s * (1.0 + self.rng.uniform(-self.jitter, self.jitter))
        self.queue.append((now + delay, packet))

    def receive(self, now: float) -> list[Any]:
        out = [p for t, p in self.queue if t <= now]
        if out:
            self.queue = [(t, p) for t, p in self.queue if t > now]
        return out


class TipFollower:
    """One arm's tip follows a target (m, base frame) at a fixed orientation (damped least
    squares on the arm's Jacobian; tip ≤ 0.5 m/s, joints ≤ 3 rad/s); an arm of fewer than six
    joints follows the position only. The backend's other arms hold their joints."""

    def __init__(self, backend: MujocoBackend, model: str = "mh3f", arm: str = "arm1") -> None:
        self.profile = registry.arm_profile(model, arm)
        self.backend = backend
        names = list(backend.joint_names)
        self._index = [names.index(j) for j in self.profile.model_joints]
        self._q_all = backend.read().position.copy()
        self.q = self._q_all[self._index].copy()

    def tip(self) -> np.ndarray:
        out: np.ndarray = self.profile.pose(self.q)[:3, 3]
        return out

    def measured(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The arm's measured tip (m) and the contact wrench on its instrument (N, N·m; None:
        the backend measures no contact)."""
        r, site = self.backend.read(), self.profile.tip_site
        tip = r.tip_position
        if r.site_positions is not None and site in self.backend.sites:
            tip = r.site_positions[self.backend.sites.index(site)]
        return tip.copy(), None if r.site_wrenches is None else r.site_wrenches.get(site)

    def follow(self, target: np.ndarray) -> None:
        jac = self.profile.jacobian(self.q)
        step = target - self.tip()
        n = float(np.linalg.norm(step))
        if n > 0.0005:  # at most 0.5 m/s: a far target is approached along a line
            step *= 0.0005 / n
        err = np.r_[step, np.zeros(3)]
        if len(self.q) < 6:  # too few joints to hold an orientation too
            jac, err = jac[:3], step
        dq = np.linalg.solve(jac.T @ jac + 1e-6 * np.eye(len(self.q)), jac.T @ err)
        big = float(np.max(np.abs(dq)))
        self.q = self.q + (dq * (0.003 / big) if big > 0.003 else dq)
        self._q_all[self._index] = self.q
        self.backend.command(self._q_all)
        self.backend.step(1)


def contact_height(backend: MujocoBackend, follower: TipFollower) -> float:
    """m: the tip's z where the tissue first pushes back (lowered at 10 mm/s from where it is)."""
    z = follower.tip()[2]
    x0 = follower.tip().copy()
    while z > x0[2] - 0.08:
        z -= 1e-5
        follower.follow(np.array([x0[0], x0[1], z]))
        tip, w = follower.measured()
        if w is not None and w[2] > 0.05:
            return float(tip[2])
    raise RuntimeError("the tip never touched the tissue: is the scene's tissue touchable?")


def tissue_stiffness(backend: MujocoBackend, follower: TipFollower, z_contact: float) -> float:
    """N/m: the tissue's stiffness where the bench presses (quasi-static, 2–8 mm deep)."""
    x0 = follower.tip().copy()
    depths, forces = [], []
    for mm in (2.0, 4.0, 6.0, 8.0):
        target = np.array([x0[0], x0[1], z_contact - mm / 1e3])
        for _ in range(400):
            follower.follow(target)
        tip, w = follower.measured()
        if w is None:
            raise RuntimeError("the slave backend measures no contact")
        depths.append(z_contact - float(tip[2]))
        forces.append(float(w[2]))
    return float(np.polyfit(depths, forces, 1)[0])


def run_one(
    controller: str,
    round_trip_ms: float,
    jitter: float = 0.0,
    loss: float = 0.0,
    cut_back_at: float | None = None,
    seed: int = 1,
    bil_cfg: BilateralConfig | None = None,
    render_cfg: RenderConfig | None = None,
    k_tissue: float | None = None,
) -> dict[str, Any]:
    """One press-and-slide run; its figures (see the module doc)."""
    bil_cfg = bil_cfg or BilateralConfig(controller=controller)
    if bil_cfg.controller != controller:
        bil_cfg = BilateralConfig(**{**bil_cfg.__dict__, "controller": controller})
    render_cfg = render_cfg or RenderConfig()
    rng = random.Random(seed)
    fwd = Channel(round_trip_ms / 2e3, jitter, loss, rng)
    back = Channel(round_trip_ms / 2e3, jitter, loss, rng)
    if cut_back_at is not None:
        back.cut_at = cut_back_at
    profile = registry.arm_profile("mh3f", "arm1")
    with MujocoBackend("mh3f", profile.home) as backend:
        follower = TipFollower(backend)
        z_c = contact_height(backend, follower)
        if k_tissue is None:
            k_tissue = tissue_stiffness(backend, follower, z_c)
        x0 = follower.tip().copy()
        anchor = np.array([x0[0], x0[1], z_c + ABOVE_MM / 1e3])
        for _ in range(1500):  # to the anchor, then settle
            follower.follow(anchor)
        device = HeldDevice(TouchModel(force_limit_n=render_cfg.limit_n), press_and_slide(-ABOVE_MM))
        bil = make_bilateral(bil_cfg)
        slave_bil = make_bilateral(bil_cfg)  # the slave side's own instance: no shared state
        renderer = ForceRenderer(render_cfg)
        n = int(END / DT)
        log = np.zeros((n, 14))
        last_rx = -np.inf
        for k in range(n):
            t = k * DT
            # master side: the haptic loop
            rx_s: list[SlavePacket] = back.receive(t)
            if rx_s:
                last_rx = t
            newest_s = max(rx_s, key=lambda p: p.seq) if rx_s else None
            f_cmd = bil.master_step(device.x, device.v, newest_s, DT)
            renderer.offer(f_cmd, last_rx)
            shaped = renderer.step(t, DT)
            if not renderer.fading:  # while fading the force only goes to zero
                shaped = bil.master_passivity(shaped, device.v, DT)
            f_dev = device.write_force(shaped)
            fwd.send(bil.master_sent(f_dev, device.x, device.v, DT), t)
            x_m = device.x.copy()
            device.step(DT)
            # slave side
            rx_m: list[MasterPacket] = fwd.receive(t)
            newest_m = max(rx_m, key=lambda p: p.seq) if rx_m else None
            w = backend.read().contact_wrench
            f_e = w[:3].copy() if w is not None else np.zeros(3)
            x_s = slave_bil.slave_step(newest_m, f_e, DT)
            follower.follow(anchor + x_s)
            if k % FORCE_EVERY == 0:
                back.send(slave_bil.slave_packet(f_e), t)
            tip = backend.read().tip_position
            log[k] = (
                t,
                x_m[0],
                x_m[2],
                f_dev[0],
                f_dev[2],
                f_e[0],
                f_e[2],
                tip[0] - anchor[0],
                tip[2] - anchor[2],
                bil.observed_master,
                slave_bil.observed_slave,
                float(np.linalg.norm(slave_bil.drift)),
                float(np.linalg.norm(f_dev)),
                f_cmd[2],
            )
    return summarise(
        controller, round_trip_ms, jitter, loss, log, k_tissue, bil_cfg, renderer, cut_back_at
    ) | {"_log": log}


def _window(log: np.ndarray, a: float, b: float) -> np.ndarray:
    out: np.ndarray = log[(log[:, 0] >= a) & (log[:, 0] < b)]
    return out


def _hp_rms(x: np.ndarray, hz: float = 2.0) -> float:
    """RMS of ``x`` (sampled at 1 kHz) above ``hz``, its linear trend removed first (in a short
    window a ramp would otherwise count as content above 2 Hz)."""
    if len(x) < 8:
        return 0.0
    t = np.arange(len(x))
    spec = np.fft.rfft(x - np.polyval(np.polyfit(t, x, 1), t))
    freqs = np.fft.rfftfreq(len(x), DT)
    spec[freqs < hz] = 0.0
    return float(np.sqrt(np.mean(np.fft.irfft(spec, len(x)) ** 2)))


def summarise(
    controller: str,
    rt_ms: float,
    jitter: float,
    loss: float,
    log: np.ndarray,
    k_tissue: float,
    cfg: BilateralConfig,
    renderer: ForceRenderer,
    cut_back_at: float | None,
) -> dict[str, Any]:
    """The figures of one run (module doc)."""
    hold = _window(log, *HOLD)
    steady = float(np.mean(hold[:, 6])) if len(hold) else 0.0
    press = _window(log, PRESS[0], HOLD[1])
    peak = float(np.max(press[:, 6])) if len(press) else 0.0
    contact = _window(log, PRESS[0] + 0.5, SLIDE[1])
    osc = _hp_rms(contact[:, 6])
    late = _hp_rms(_window(log, SLIDE[1] - 0.5, SLIDE[1])[:, 6])
    early = _hp_rms(_window(log, HOLD[0] - 0.5, HOLD[0])[:, 6])
    free = _window(log, 0.0, PRESS[0] - 0.2)
    # perceived stiffness: master force vs master position while in contact and pressing
    sel = (press[:, 6] > 0.3) & (press[:, 0] < 2.6)
    felt = (
        float(-np.polyfit(press[sel, 2], press[sel, 4], 1)[0]) if np.count_nonzero(sel) > 50 else float("nan")
    )
    expected = cfg.force_scale * cfg.position_scale * k_tissue
    overshoot = peak / steady if steady > 0.05 else float("inf")
    w_m, w_s = float(np.min(log[:, 9])), float(np.min(log[:, 10]))
    row: dict[str, Any] = {
        "controller": controller,
        "round_trip_ms": rt_ms,
        "jitter": jitter,
        "loss": loss,
        "steady_n": round(steady, 3),
        "peak_n": round(peak, 3),
        "overshoot": round(overshoot, 2) if np.isfinite(overshoot) else None,
        "osc_rms_n": round(osc, 4),
        "osc_growth": round(late / early, 2) if early > 1e-4 else None,
        "min_observed_master_mj": round(w_m * 1e3, 3),
        "min_observed_slave_mj": round(w_s * 1e3, 3),
        "drift_max_mm": round(float(np.max(log[:, 11])) * 1e3, 2),
        "drift_end_mm": round(float(log[-1, 11]) * 1e3, 2),
        "felt_stiffness_n_per_mm": round(felt / 1e3, 4) if np.isfinite(felt) else None,
        "expected_stiffness_n_per_mm": round(expected / 1e3, 4),
        "free_space_force_n": round(float(np.max(free[:, 12])), 4),
        "max_device_force_n": round(float(np.max(log[:, 12])), 3),
        "device_limit_n": renderer.cfg.limit_n,
        "limit_clipped_periods": renderer.clipped,
    }
    if cut_back_at is not None:
        after = _window(log, cut_back_at, cut_back_at + 1.0)
        rate = np.abs(np.diff(after[:, 12])) / DT
        row["cut_back_at_s"] = cut_back_at
        row["fade_max_rate_n_per_s"] = round(float(np.max(rate)), 2) if len(rate) else None
        zero = after[after[:, 12] < 1e-3]
        row["faded_to_zero_s"] = round(float(zero[0, 0] - cut_back_at), 3) if len(zero) else None
    # sustained: still above 0.05 N rms in the last quarter second of the final hold and not
    # decaying there (a transient the slide left, dying out, is not an oscillation that grows)
    last = _hp_rms(_window(log, SLIDE[1] - 0.25, SLIDE[1])[:, 6])
    before = _hp_rms(_window(log, SLIDE[1] - 0.5, SLIDE[1] - 0.25)[:, 6])
    row["osc_end_n"] = round(last, 4)
    growing = (row["osc_growth"] or 0) > 1.5 and last > 0.05 and last >= 0.8 * before
    row["verdict"], row["unstable_because"] = judge(
        overshoot, growing, osc, min(w_m, w_s) * 1e3, cfg.controller
    )
    return row


def judge(
    overshoot: float, growing: bool, osc: float, w_min_mj: float, controller: str
) -> tuple[str, list[str]]:
    """The verdict of one run and the reasons of an ``unstable`` one: ``unstable`` (overshoot > 3×,
    a growing oscillation, an oscillation above 0.5 N rms, or, with feedback on, an observer below
    −10 mJ: the network generated energy), ``stable`` (overshoot ≤ 1.5, oscillation < 0.2 N rms, not
    growing, observers ≥ −1 mJ) or ``marginal``. Without feedback no loop closes through the hand:
    the slave's observer then only says the tissue got work the hand never felt."""
    why = [
        reason
        for reason, hit in (
            ("overshoot > 3× steady", overshoot > 3.0),
            ("growing oscillation", growing),
            ("oscillation > 0.5 N rms", osc > 0.5),
            ("the network generated > 10 mJ", controller != "none" and w_min_mj < -10.0),
        )
        if hit
    ]
    if why:
        return "unstable", why
    stable = bool(np.isfinite(overshoot)) and overshoot <= 1.5 and osc < 0.2 and not growing
    stable = stable and w_min_mj >= -1.0
    return ("stable" if stable else "marginal"), []


def plot(rows: list[dict[str, Any]], logs: dict[tuple[str, float], np.ndarray], out: Path) -> None:
    """Contact force over time for each controller at a few round trips, and overshoot vs delay."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    show = [rt for rt in (0, 100, 400) if any(k[1] == rt for k in logs)]
    ctrls = [c for c in CONTROLLERS if any(k[0] == c for k in logs)]
    fig, axes = plt.subplots(len(ctrls) + 1, 1, figsize=(9, 2.3 * (len(ctrls) + 1)), squeeze=False)
    for ax, c in zip(axes[:-1, 0], ctrls, strict=False):
        for rt in show:
            log = logs.get((c, rt))
            if log is not None:
                ax.plot(log[:, 0], log[:, 6], lw=1.0, label=f"{rt:g} ms")
        ax.set_ylabel(f"{c}\ncontact N")
        ax.set_ylim(-0.5, 8)
        ax.legend(fontsize=7, loc="upper right")
    ax = axes[-1, 0]
    for c in ctrls:
        pts = [
            (r["round_trip_ms"], r["overshoot"] or 10.0)
            for r in rows
            if r["controller"] == c and r["jitter"] == 0
        ]
        if pts:
            xs, ys = zip(*pts, strict=False)
            ax.plot(xs, ys, marker="o", label=c)
    ax.set_xscale("symlog", linthresh=10)
    ax.set_yscale("log")
    ax.axhline(1.5, color="grey", ls="--", lw=0.8)
    ax.axhline(3.0, color="red", ls="--", lw=0.8)
    ax.set_xlabel("round trip (ms); contact-force overshoot (peak / steady), clean channel")
    ax.legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)


def diagram(out: Path) -> None:
    """The architecture picture of docs/haptics.md (``--diagram FILE``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyBboxPatch

    fig, ax = plt.subplots(figsize=(11, 4.2))
    ax.set_xlim(0, 11.3)
    ax.set_ylim(0, 4.2)
    ax.axis("off")
    boxes = {
        "hand": (0.2, 1.6, "operator's hand\n(spring-damper to\nthe scripted intent)"),
        "device": (2.0, 1.6, "touch_sim device\n45 g, 0.1 N friction\nlimit 3.3 N"),
        "loop": (3.9, 1.6, "haptic loop 1 kHz\ncheck · fade · rate\nlimit · master PC"),
        "net": (5.9, 1.6, "network\ndelay ± jitter, loss\n(bench: in-process)"),
        "slave": (7.7, 1.6, "slave side\nslave PC · drift comp.\ntip follower 1 kHz"),
        "mujoco": (9.5, 1.6, "MuJoCo MH3F\ntissue 0.4 N/mm\ncontact wrench"),
    }
    for x, y, text in boxes.values():
        ax.add_patch(FancyBboxPatch((x, y), 1.5, 1.1, boxstyle="round,pad=0.05", fc="#eaf2f8", ec="#20639b"))
        ax.text(x + 0.75, y + 0.55, text, ha="center", va="center", fontsize=7.5)
    names = list(boxes)
    for a, b in itertools.pairwise(names):
        xa, ya, _ = boxes[a]
        xb, _, _ = boxes[b]
        ax.annotate(
            "", (xb, ya + 0.8), (xa + 1.5, ya + 0.8), arrowprops={"arrowstyle": "->", "color": "#173f5f"}
        )
        ax.annotate(
            "", (xa + 1.5, ya + 0.3), (xb, ya + 0.3), arrowprops={"arrowstyle": "->", "color": "#ed553b"}
        )
    ax.text(5.5, 3.3, "x_m, E_in_m  →  (measured_cp.energy_in_j)", ha="center", color="#173f5f", fontsize=9)
    ax.text(
        5.5,
        1.0,
        "←  f_e, E_in_s  (measured_cf at 500 Hz, .energy_in_j)",
        ha="center",
        color="#ed553b",
        fontsize=9,
    )
    ax.text(
        5.5,
        0.4,
        "observers W_m = E_in_s(k−D_b) − E_out_m,  W_s = E_in_m(k−D_f) − E_out_s;  "
        "watchdog: tip_force rule on measured_cf (DEGRADED → HOLD)",
        ha="center",
        fontsize=8,
    )
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="telesurg bench haptics", description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--plot", type=Path, help="write the figure here (PNG)")
    ap.add_argument(
        "--quick",
        action="store_true",
        help="0, 100 and 400 ms, clean channel (--services: 0 and 100 ms, tdpa, naive)",
    )
    ap.add_argument("--controllers", help="comma-separated subset (default: all of the mode's)")
    ap.add_argument("--diagram", type=Path, help="only draw the architecture picture (PNG) here")
    ap.add_argument(
        "--services", action="store_true", help="through the real services, one local site per run"
    )
    ap.add_argument(
        "--round-trips-ms", help="--services: comma-separated round trips (default 0,10,25,50,100,200,400)"
    )
    ap.add_argument("--jitter", type=float, default=0.0, help="--services: per-chunk delay × (1 ± this)")
    ap.add_argument("--log-dir", type=Path, help="--services: keep each run's service logs here")
    ap.add_argument(
        "--retries",
        type=int,
        default=1,
        help="--services: runs again a run the host's load disturbed (holds)",
    )
    args = ap.parse_args(argv)
    if args.diagram:
        diagram(args.diagram)
        return 0
    if args.services:
        from telesurg.tools.bench import haptics_services

        valid: Sequence[str] = haptics_services.CONTROLLERS
        default = "tdpa,naive" if args.quick else ",".join(valid)
    else:
        valid, default = CONTROLLERS, ",".join(CONTROLLERS)
    ctrls = [c for c in (args.controllers or default).split(",") if c]
    bad = [c for c in ctrls if c not in valid]
    if bad:
        ap.error(f"unknown controller(s) {', '.join(bad)}; valid: {', '.join(valid)}")
    if args.services:
        try:
            trips = [float(v) for v in (args.round_trips_ms or "").split(",") if v.strip()]
        except ValueError:
            ap.error(f"--round-trips-ms: numbers in ms, comma-separated, not {args.round_trips_ms!r}")
        if not trips:
            trips = [0.0, 100.0] if args.quick else [float(v) for v in haptics_services.ROUND_TRIPS_MS]
        if any(v < 0 for v in trips) or args.retries < 0 or not 0.0 <= args.jitter < 1.0:
            ap.error("round trips must be ≥ 0 ms, --jitter in [0, 1), --retries ≥ 0")
        return haptics_services.main(args, ctrls, trips)
    if args.round_trips_ms or args.jitter or args.log_dir or args.retries != 1:
        ap.error("--round-trips-ms, --jitter, --log-dir and --retries go with --services")
    rts = (0, 100, 400) if args.quick else ROUND_TRIPS_MS
    impairments = [(0.0, 0.0)] if args.quick else [(0.0, 0.0), (0.2, 0.05)]
    t0 = time.perf_counter()
    # the tissue's stiffness, measured once (quasi-static)
    with MujocoBackend("mh3f", registry.arm_profile("mh3f", "arm1").home) as backend:
        follower = TipFollower(backend)
        k = tissue_stiffness(backend, follower, contact_height(backend, follower))
    rows: list[dict[str, Any]] = []
    logs: dict[tuple[str, float], np.ndarray] = {}
    print(f"tissue stiffness {k / 1e3:.3f} N/mm")
    header = f"{'ctrl':<6}{'rt ms':>6}{'jit':>5}{'loss':>5}{'steady N':>9}{'overshoot':>10}{'osc N':>8}"
    print(header + f"{'Wm mJ':>9}{'Ws mJ':>9}{'drift mm':>9}{'felt/exp':>10}{'free N':>8}  verdict")
    for jitter, loss in impairments:
        for c in ctrls:
            for rt in rts:
                r = run_one(c, rt, jitter, loss, k_tissue=k)
                log = r.pop("_log")
                if jitter == 0:
                    logs[(c, rt)] = log
                rows.append(r)
                ratio = (
                    f"{r['felt_stiffness_n_per_mm'] / r['expected_stiffness_n_per_mm']:.2f}"
                    if r["felt_stiffness_n_per_mm"]
                    else "-"
                )
                print(
                    f"{c:<6}{rt:>6}{jitter:>5.2f}{loss:>5.2f}{r['steady_n']:>9.3f}"
                    f"{r['overshoot'] or float('inf'):>10.2f}"
                    f"{r['osc_rms_n']:>8.3f}{r['min_observed_master_mj']:>9.2f}{r['min_observed_slave_mj']:>9.2f}"
                    f"{r['drift_max_mm']:>9.2f}{ratio:>10}{r['free_space_force_n']:>8.3f}  {r['verdict']}",
                    flush=True,
                )
    fade = run_one("tdpa", 50, cut_back_at=3.0, k_tissue=k)
    fade.pop("_log")
    print(
        f"force stream cut at 3.0 s (tdpa, 50 ms): fade ≤ {fade['fade_max_rate_n_per_s']} N/s, "
        f"zero after {fade['faded_to_zero_s']} s"
    )
    result = {
        "bench": "haptics",
        "in_process": True,
        "tissue_stiffness_n_per_mm": round(k / 1e3, 4),
        "config": {"bilateral": BilateralConfig().__dict__, "render": RenderConfig().__dict__},
        "rows": rows,
        "stale_fade": fade,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    if args.plot:
        plot(rows, logs, args.plot)
    return 0
