"""``telesurg bench haptics --services``: the press and slide through the real services.

One local site per run, on loopback: router, watchdog, slave_control (the MuJoCo MH3F with its
touchable tissue) and the mapping (at scale 1; for TDPA with the slave's passivity controller,
``mapping.slave_passivity``), and master_capture with the simulated Touch and hand (``touch_sim``,
operator ``site``: it presses the pedal when the arm is ready and plays the press-and-slide script
while engaged) and the haptic loop (``haptics.controller``). master_capture reaches the router
only through the link impairer (:class:`~telesurg.tools.bench.impair.ImpairerProcess`), set to half
the round trip each way and, with ``--jitter``, that × (1 ± jitter) per chunk, in order. A TCP
proxy loses nothing: loss is the in-process bench's. The watchdog's latency budget and limit are
raised by the one-way delay, so the delay itself does not scale the motion down or hold.

The bench process records what the site shows (the slave's contact force ``measured_cf``, the
master's pose and its port energy ``energy_in_j``, the slave's tip, its operating state, the
watchdog's state); the mapping says at exit what its slave passivity controller saw (TDPA).
:func:`analyse` turns the records into the figures, on the operator's script clock (the script
plays only while engaged, so a hold pauses it); ``tests/test_haptics_two_hosts.py`` uses the same.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from telesurg.shared.bus import Node
from telesurg.shared.messages import CartesianPose, CartesianWrench, OperatingState, SafetyState
from telesurg.tools.bench.haptics import judge

#: the controllers run through the services (wave has no slave side in the mapping)
CONTROLLERS = ("none", "naive", "tdpa")
ROUND_TRIPS_MS = (0, 10, 25, 50, 100, 200, 400)
SCALE = 1.0  # the mapping's scale: the tissue is 40 mm below the tip's home (a Touch's reach at 1:1)
FORCE_SCALE = 0.5  # master force per slave contact force (haptics.force_scale default)
TISSUE_LIMIT_N = 4.0  # the watchdog's tip_force limit (default)
SCRIPT_S = 7.3  # the touch_sim script's length while engaged (press_and_slide)
SLIDE_MM = 20.0
#: mm the operator means to press beyond the surface: a firm press well inside the tissue limit
#: (the in-process bench's 11 mm gives ~2.4 N steady at 0.4 N/mm, and the slide on the crest 4 N)
PRESS_MM = 6.0
#: Hz: the console's pose stream (its haptic loop stays at 1 kHz): 4 ms against a link's tens of
#: ms, and half the default's traffic through the impairer
MASTER_HZ = 250.0
#: s of script time (touch_sim.model.press_and_slide): the press's hold, the final hold
PRESS_HOLD_S = (2.3, 3.8)
FINAL_HOLD_S = (5.3, 6.3)
#: what the mapping (TDPA's slave port) and master_capture (the master port) say at exit
SPC_LINE = re.compile(r"slave passivity: observed W_s min (\S+) mJ, dissipated (\S+) mJ, drift max (\S+) mm")
MPC_LINE = re.compile(r"master passivity: observed W_m min (\S+) mJ, dissipated (\S+) mJ")


def tissue_top_z() -> float:
    """m: the top of the MH3F scene's tissue where the instrument reaches it (its ellipsoid's
    crest), from the scene the slave simulates."""
    import mujoco
    from telesurg.shared.robots import registry

    model = mujoco.MjModel.from_xml_path(str(registry.get("mh3f").scene))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    geom = model.geom("tissue")
    return float(data.geom_xpos[geom.id][2] + model.geom_size[geom.id][2])


def home_tip() -> np.ndarray:
    """m, base frame: the MH3F arm1's tip at its home joints (where slave_control starts)."""
    from telesurg.services.slave_control.backends import MujocoBackend
    from telesurg.shared.robots import registry

    profile = registry.arm_profile("mh3f", "arm1")
    with MujocoBackend("mh3f", profile.home) as backend:
        r = backend.read()
        tip = r.tip_position
        if r.site_positions is not None and profile.tip_site in backend.sites:
            tip = r.site_positions[backend.sites.index(profile.tip_site)]
        return np.array(tip, dtype=float)


def hf_rms(t: np.ndarray, f: np.ndarray) -> float:
    """N: RMS of ``f`` above ~2 Hz (``f`` minus its 0.25 s moving mean), over samples at times ``t``."""
    if len(f) < 10:
        return 0.0
    win = min(len(f) // 2, max(3, round(0.25 / max(float(np.median(np.diff(t))), 1e-4))))
    mean = np.convolve(f, np.ones(win) / win, mode="same")
    core = slice(win // 2, len(f) - win // 2)
    return float(np.sqrt(np.mean((f[core] - mean[core]) ** 2)))


def script_clock(recs: list[dict[str, Any]], t_follow: int) -> tuple[np.ndarray, np.ndarray]:
    """The operator's script clock: (monotonic s, script s) at each of the slave's operating-state
    records from the first follow. The script plays only while the pair is engaged (a hold
    pauses it, module doc of touch_sim), so its time is the engaged time since the first follow."""
    ops = [(r["t"] / 1e9, bool(r["follow"])) for r in recs if r["k"] == "op" and r["t"] >= t_follow]
    t = np.array([o[0] for o in ops])
    on = np.array([o[1] for o in ops], dtype=float)
    played = np.concatenate([[0.0], np.cumsum(np.diff(t) * on[:-1])])
    return t, played


def console_settings(surface_mm: float, controller: str) -> list[str]:
    """master_capture's settings of the haptic console that presses and slides: the simulated
    Touch held by the scripted operator (``surface_mm`` below its start, in the master frame), the
    haptic loop on arm1 with ``controller``, the pose at :data:`MASTER_HZ`."""
    return [
        'device="touch_sim"',
        'device_options.operator="site"',
        f"device_options.surface_mm={surface_mm:.1f}",
        f"device_options.slide_mm={SLIDE_MM}",
        f"device_options.press_mm={PRESS_MM}",
        'haptics.slave_arm="arm1"',
        f"haptics.controller={json.dumps(controller)}",
        f"haptics.force_scale={FORCE_SCALE}",
        f"rate_hz={MASTER_HZ:g}",
    ]


def analyse(recs: list[dict[str, Any]], t_follow: int, lag_s: float, scale: float = SCALE) -> dict[str, Any]:
    """The figures of one press and slide from the records (monotonic ns ``t``), phased by the
    operator's script clock, the slave's force ``lag_s`` behind it (the link's delay): the
    steady force is the median over the press's last 0.5 s of holding, the overshoot the largest
    force until then over it; the oscillation is over that hold, its growth the final hold's
    end against the press's; the drift is where the slave ended against where the master
    (× ``scale``) went."""
    cf = [(r["t"], *r["f"]) for r in recs if r["k"] == "cf" and r["t"] >= t_follow]
    mp = [(r["t"], *r["p"], r["e"]) for r in recs if r["k"] == "mp" and r["t"] >= t_follow]
    tip = [(r["t"], *r["p"]) for r in recs if r["k"] == "tip"]
    c, m, p = np.array(cf, dtype=float), np.array(mp, dtype=float), np.array(tip, dtype=float)
    tc, fz, fn = c[:, 0] / 1e9, c[:, 3], np.linalg.norm(c[:, 1:4], axis=1)
    mz, energy = m[:, 3], m[:, 4]
    clock_t, clock_s = script_clock(recs, t_follow)
    sc = np.interp(tc, clock_t, clock_s) - lag_s  # each contact-force sample's script time

    def window(a: float, b: float) -> np.ndarray:
        out: np.ndarray = (sc >= a) & (sc <= b)
        return out

    settled = window(PRESS_HOLD_S[1] - 0.5, PRESS_HOLD_S[1])
    if settled.sum() < 10:
        raise RuntimeError(f"too few contact samples in the press's hold: {int(settled.sum())}")
    steady = float(np.median(fz[settled]))
    pressing = sc <= PRESS_HOLD_S[1]  # reach, press and its hold
    overshoot = float(fz[pressing].max() / steady) if steady > 0 else float("inf")
    early = window(PRESS_HOLD_S[1] - 0.5, PRESS_HOLD_S[1])
    late = window(FINAL_HOLD_S[1] - 0.5, FINAL_HOLD_S[1])
    osc_early, osc_late = hf_rms(tc[early], fz[early]), hf_rms(tc[late], fz[late])
    # drift: where the slave went against where the master (× scale) went, after the release
    home = p[p[:, 0] < t_follow][-1, 1:4] if (p[:, 0] < t_follow).any() else p[0, 1:4]
    end_t = p[-1, 0]
    slave_end = p[-1, 1:4]
    master_end = m[m[:, 0] <= end_t][-1, 1:4]
    drift = slave_end - (home + scale * (master_end - m[0, 1:4]))
    return {
        "steady_force_n": round(steady, 3),
        "overshoot": round(overshoot, 3) if np.isfinite(overshoot) else None,
        "hold_oscillation_rms_n": round(osc_early, 4),
        "final_hold_oscillation_rms_n": round(osc_late, 4),
        "osc_growth": round(osc_late / osc_early, 2) if osc_early > 1e-4 else None,
        "largest_force_n": round(float(fn.max()), 3),
        "master_energy_min_mj": round(float(energy.min()) * 1e3, 3),
        "master_energy_end_mj": round(float(energy[-1]) * 1e3, 3),
        "press_mm_master": round((float(m[0, 3]) - float(mz.min())) * 1e3, 2),
        "drift_mm": [round(float(v) * 1e3, 2) for v in drift],
        "drift_norm_mm": round(float(np.linalg.norm(drift)) * 1e3, 2),
        "engaged_s": round(float(clock_s[-1]), 2),
        "samples": {"cf": len(c), "mp": len(m), "tip": len(p)},
    }


def verdict(fig: dict[str, Any], controller: str) -> tuple[str, list[str]]:
    """The in-process bench's rules on a services run: ``unstable`` (overshoot > 3×, a growing
    oscillation, an oscillation above 0.5 N rms, a port's observer below −10 mJ with feedback on),
    ``stable`` (overshoot ≤ 1.5, hold oscillation < 0.2 N rms, not growing, observers ≥ −1 mJ) or
    ``marginal``; the reasons of an ``unstable``. The observers: W_m, master_capture's, and W_s,
    the mapping's slave passivity controller's (TDPA only), as they say at exit."""
    overshoot = fig["overshoot"] if fig["overshoot"] is not None else float("inf")
    osc = max(fig["hold_oscillation_rms_n"], fig["final_hold_oscillation_rms_n"])
    w_min = min(fig.get("master_observed_min_mj", 0.0), fig.get("slave_energy_min_mj", 0.0))
    growing = (fig["osc_growth"] or 0.0) > 1.5 and fig["final_hold_oscillation_rms_n"] > 0.05
    return judge(overshoot, growing, osc, w_min, controller)


class Recorder:
    """What the site shows, one dict per message (``t``: this process's monotonic ns, ``k``: the
    kind): ``cf`` contact force, ``mp`` master pose and energy, ``tip`` (≤ 100 Hz), ``op``
    operating state, ``safety`` the watchdog's state."""

    def __init__(self, node: Node, arm: str = "arm1", master: str = "m1") -> None:
        self.lock = threading.Lock()
        self.recs: list[dict[str, Any]] = []
        self._last_tip = 0
        k, sub = node.keys, node.subscribe
        slave = ["slave_control"]
        sub(k.slave(arm, "measured_cf"), CartesianWrench, self._cf, sources=slave)
        sub(k.slave(arm, "measured_cp"), CartesianPose, self._tip, sources=slave)
        sub(k.slave(arm, "operating_state"), OperatingState, self._op, sources=slave)
        sub(k.master(master, "measured_cp"), CartesianPose, self._mp, sources=["master_capture"])
        sub(k.safety(arm, "state"), SafetyState, self._safety, sources=["watchdog"])

    def _add(self, **rec: Any) -> None:
        rec["t"] = time.monotonic_ns()
        with self.lock:
            self.recs.append(rec)

    def _cf(self, m: CartesianWrench, key: str) -> None:
        self._add(k="cf", f=list(m.force))

    def _mp(self, m: CartesianPose, key: str) -> None:
        self._add(k="mp", p=list(m.position), e=m.energy_in_j)

    def _tip(self, m: CartesianPose, key: str) -> None:
        now = time.monotonic_ns()
        if now - self._last_tip >= 10_000_000:
            self._last_tip = now
            self._add(k="tip", p=list(m.position))

    def _op(self, m: OperatingState, key: str) -> None:
        self._add(k="op", follow=m.follow, state=m.state, reason=m.reason)

    def _safety(self, m: SafetyState, key: str) -> None:
        self._add(k="safety", state=m.state, causes=list(m.causes), scale=m.scale)

    def first(self, kind: str, pred: Any = None) -> dict[str, Any] | None:
        """The first record of ``kind`` (matching ``pred``)."""
        with self.lock:
            return next((r for r in self.recs if r["k"] == kind and (pred is None or pred(r))), None)

    def following(self) -> bool:
        """The slave's last operating state says it follows."""
        with self.lock:
            ops = [r for r in self.recs[-400:] if r["k"] == "op"]
        return bool(ops) and bool(ops[-1]["follow"])

    def wait(self, kind: str, pred: Any, timeout: float) -> dict[str, Any] | None:
        """Poll for the first record of ``kind`` matching ``pred``."""
        deadline = time.monotonic() + timeout
        while (r := self.first(kind, pred)) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        return r


def run_one(controller: str, round_trip_ms: float, log_dir: Path, jitter: float = 0.0) -> dict[str, Any]:
    """One press and slide through a site of its own (module doc); its figures and verdict. The
    site is stopped before this returns."""
    from telesurg.tools.bench.harness import Pipeline
    from telesurg.tools.bench.netprofile import LinkProfile

    one_way = round_trip_ms / 2.0
    surface_mm = (tissue_top_z() - float(home_tip()[2])) / SCALE * 1e3
    watchdog = [
        f"rules.tip_force.limit_n={TISSUE_LIMIT_N}",
        f"latency_budget_ms={one_way + 150.0:g}",
        f"latency_limit_ms={one_way + 300.0:g}",
    ]
    if jitter > 0:  # chunks bunch behind a late one: the master's stream may pause 2 × the jitter
        gap = 2.0 * one_way * jitter
        watchdog += [f"master_deadline_ms={80.0 + gap:g}", f"buttons_deadline_ms={200.0 + gap:g}"]
    mapping = [f"scale={SCALE}"]
    if controller == "tdpa":  # TDPA's slave port
        mapping += ["slave_passivity=true", f"haptics_force_scale={FORCE_SCALE}"]
    master = console_settings(surface_mm, controller)
    overrides = {"watchdog": watchdog, "mapping": mapping, "master_capture": master}
    row: dict[str, Any] = {"controller": controller, "round_trip_ms": round_trip_ms, "jitter": jitter}
    link = LinkProfile(delay_ms=one_way, jitter_ms=one_way * jitter)
    with Pipeline(log_dir, overrides=overrides, mirror=False, probe=False, link=link) as pipe:
        rec = Recorder(pipe.node)
        home = rec.wait("tip", lambda r: True, 20.0)
        follow = rec.wait("op", lambda r: r["follow"], 90.0)
        if home is None or follow is None:
            raise RuntimeError(f"the slave never followed the haptic master\n{pipe.diagnose()}")
        # the script plays while engaged: wait for it to end (a hold pauses it), then a second more
        deadline, engaged = time.monotonic() + 60.0, 0.0
        while engaged < SCRIPT_S + 1.0 and time.monotonic() < deadline:
            time.sleep(0.25)
            engaged += 0.25 if rec.following() else 0.0
        mc = pipe.site.procs["master_capture"]
        mc.send_signal(signal.SIGINT)
        try:
            row["master_exit"] = mc.wait(10.0)
        except subprocess.TimeoutExpired:
            mc.kill()
            row["master_exit"] = mc.wait()
        with rec.lock:
            recs = list(rec.recs)
        row["exit_codes"] = pipe.close()
    row.update(analyse(recs, follow["t"], round_trip_ms / 1e3))
    spc = SPC_LINE.search((log_dir / "mapping.log").read_text(errors="replace"))
    if spc is not None:
        w_s, dissipated, drift = (float(v) for v in spc.groups())
        row |= {"slave_energy_min_mj": w_s, "slave_dissipated_mj": dissipated, "slave_drift_max_mm": drift}
    mpc = MPC_LINE.search((log_dir / "master_capture.log").read_text(errors="replace"))
    if mpc is not None:
        row["master_observed_min_mj"], row["master_dissipated_mj"] = (float(v) for v in mpc.groups())
    safety = [r for r in recs if r["k"] == "safety" and r["t"] >= follow["t"]]
    row["states"] = sorted({r["state"] for r in safety})
    row["tissue_limit_reached"] = any(any("tip force" in c for c in r["causes"]) for r in safety)
    row["holds"] = [
        (round((r["t"] - follow["t"]) / 1e9, 2), r["state"], r["causes"])
        for r in safety
        if r["state"] != "OK"
    ][:5]
    row["disturbed"] = disturbances(recs, follow["t"])
    row["surface_mm_master"] = round(surface_mm, 1)
    row["home_tip_mm"] = [round(float(v) * 1e3, 1) for v in home["p"]]
    row["verdict"], row["unstable_because"] = verdict(row, controller)
    row["_trace"] = _trace(recs, follow["t"], round_trip_ms / 1e3)
    return row


def disturbances(recs: list[dict[str, Any]], t_follow: int) -> list[str]:
    """What interrupted the script other than the tissue (on a loaded host: a stale stream, the
    latency budget): the watchdog's causes while it played, and the times the slave stopped
    following; empty for a clean run."""
    clock_t, clock_s = script_clock(recs, t_follow)
    done = clock_s >= SCRIPT_S
    t_end = int(clock_t[done][0] * 1e9) if done.any() else (recs[-1]["t"] if recs else t_follow)
    inside = [r for r in recs if t_follow <= r["t"] <= t_end]
    causes = sorted(
        {
            re.sub(r"[\d.]+ ms", "N ms", c)
            for r in inside
            if r["k"] == "safety" and r["state"] != "OK"
            for c in r["causes"]
            if "tip force" not in c
        }
    )
    ops = [bool(r["follow"]) for r in inside if r["k"] == "op"]
    held = sum(1 for a, b in itertools.pairwise(ops) if a and not b)
    return causes + ([f"the slave stopped following {held}×"] if held else [])


def _trace(recs: list[dict[str, Any]], t_follow: int, lag_s: float) -> np.ndarray:
    """(n, 2): script s, contact fz (N) of a run, for the plot."""
    cf = [(r["t"] / 1e9, r["f"][2]) for r in recs if r["k"] == "cf" and r["t"] >= t_follow]
    c = np.array(cf, dtype=float).reshape(-1, 2)
    clock_t, clock_s = script_clock(recs, t_follow)
    return np.column_stack([np.interp(c[:, 0], clock_t, clock_s) - lag_s, c[:, 1]])


def plot(rows: list[dict[str, Any]], out: Path) -> None:
    """Contact force over script time at each round trip per controller; overshoot and the
    ports' lowest energy vs round trip."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ctrls = [c for c in CONTROLLERS if any(r["controller"] == c for r in rows)]
    fig, axes = plt.subplots(len(ctrls) + 2, 1, figsize=(9, 2.3 * (len(ctrls) + 2)), squeeze=False)
    for ax, c in zip(axes[: len(ctrls), 0], ctrls, strict=True):
        for r in rows:
            if r["controller"] == c and "_trace" in r:
                ax.plot(r["_trace"][:, 0], r["_trace"][:, 1], lw=0.9, label=f"{r['round_trip_ms']:g} ms")
        ax.set_ylabel(f"{c}\ncontact N")
        ax.set_xlim(0, SCRIPT_S)
        ax.legend(fontsize=6, loc="upper right", ncol=2)
    ax_o, ax_w = axes[-2, 0], axes[-1, 0]
    for c in ctrls:
        mine = [r for r in rows if r["controller"] == c]
        xs = [r["round_trip_ms"] for r in mine]
        ax_o.plot(xs, [r["overshoot"] or 10.0 for r in mine], marker="o", label=c)
        wm = [r.get("master_observed_min_mj", np.nan) for r in mine]
        ax_w.plot(xs, wm, marker="o", label=f"{c}: W_m (master port)")
        if any("slave_energy_min_mj" in r for r in mine):
            ws = [r.get("slave_energy_min_mj", np.nan) for r in mine]
            ax_w.plot(xs, ws, marker="s", ls="--", label=f"{c}: W_s (slave port)")
    for ax in (ax_o, ax_w):
        ax.set_xscale("symlog", linthresh=10)
        ax.legend(fontsize=7)
    ax_o.axhline(1.5, color="grey", ls="--", lw=0.8)
    ax_o.axhline(3.0, color="red", ls="--", lw=0.8)
    ax_o.set_ylabel("overshoot\n(peak / steady)")
    ax_w.axhline(-1.0, color="grey", ls="--", lw=0.8)
    ax_w.set_ylabel("lowest observed\nenergy (mJ)")
    ax_w.set_xlabel("round trip (ms), through the services")
    axes[len(ctrls) - 1, 0].set_xlabel("script time (s), the slave's force a round trip later")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)


def sweep(
    controllers: list[str],
    round_trips: list[float],
    jitter: float = 0.0,
    log_root: Path | None = None,
    retries: int = 1,
) -> list[dict[str, Any]]:
    """One run per controller × round trip, one site at a time; the rows, printed as they come. A
    run the host's load disturbed (:func:`disturbances`) runs again, up to ``retries`` times:
    the figures are the controller's, not the host's; the row keeps its attempts."""
    header = f"{'ctrl':<6}{'rt ms':>6}{'steady N':>9}{'overshoot':>10}{'osc N':>8}{'Wm mJ':>9}{'Ws mJ':>9}"
    print(header + f"{'drift mm':>9}{'max N':>7}{'engaged':>8}  verdict", flush=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="telesurg-haptics-services-") as tmp:
        root = log_root or Path(tmp)
        for c in controllers:
            for rt in round_trips:
                for attempt in range(1 + retries):
                    try:
                        r = run_one(c, rt, root / f"{c}-{rt:g}ms-{attempt + 1}", jitter)
                    except RuntimeError as e:  # (the site never engaged, or no press: say why)
                        if attempt == retries:
                            raise
                        print(f"{c:<6}{rt:>6g}  failed: {str(e).splitlines()[0]}", flush=True)
                        continue
                    r["attempts"] = attempt + 1
                    if not r["disturbed"]:
                        break
                    print(f"{c:<6}{rt:>6g}  disturbed: {'; '.join(r['disturbed'])}", flush=True)
                rows.append(r)
                wm, ws = r.get("master_observed_min_mj"), r.get("slave_energy_min_mj")
                print(
                    f"{c:<6}{rt:>6g}{r['steady_force_n']:>9.3f}{r['overshoot'] or float('inf'):>10.2f}"
                    f"{r['hold_oscillation_rms_n']:>8.3f}{'-' if wm is None else f'{wm:.2f}':>9}"
                    f"{'-' if ws is None else f'{ws:.2f}':>9}{r['drift_norm_mm']:>9.2f}"
                    f"{r['largest_force_n']:>7.2f}{r['engaged_s']:>8.1f}  {r['verdict']}",
                    flush=True,
                )
    return rows


def main(args: argparse.Namespace, controllers: list[str], round_trips: list[float]) -> int:
    """``telesurg bench haptics --services`` (the options parsed by :func:`haptics.main`)."""
    t0 = time.perf_counter()
    rows = sweep(controllers, round_trips, args.jitter, args.log_dir, args.retries)
    result = {
        "bench": "haptics",
        "in_process": False,
        "services": "router, watchdog, slave_control (MuJoCo MH3F), mapping; master_capture (touch_sim)",
        "link": "userspace TCP proxy on loopback: half the round trip each way, × (1 ± jitter) per chunk "
        "in order; no loss (a TCP proxy loses nothing: loss is the in-process bench's)",
        "config": {
            "scale": SCALE,
            "force_scale": FORCE_SCALE,
            "tissue_limit_n": TISSUE_LIMIT_N,
            "press_mm": PRESS_MM,
            "slide_mm": SLIDE_MM,
            "master_hz": MASTER_HZ,
            "jitter": args.jitter,
        },
        "rows": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows],
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    if args.plot:
        plot(rows, args.plot)
    return 0
