"""Feeling the tissue across two hosts: the surgeon's haptic master on the console host presses
and slides on the MH3F's tissue at the slave site, 50 ms away each way, with TDPA.

The two-host setup of ``tests/test_two_hosts.py``: the slave site (``deploy/slave-site.sh``: router
with mutual TLS and the access-control rules, watchdog, slave_control on MuJoCo, mapping) in one
network namespace behind the userspace link impairer, set to 50 ms each way; the console host
(``deploy/console.sh``) in another, running master_capture with the simulated Touch
(``touch_sim``) and the haptic loop (``haptics.slave_arm = arm1``, TDPA). The simulated operator
presses the pedal when the console says the arm is ready, then plays the bench's script while
engaged: reach the tissue, press, hold, slide 20 mm, hold, release upward.

A user notices, and the test checks: the loop is stable (no contact-force overshoot above 1.5×
the steady force, no sustained oscillation, the energy at either port never below −1 mJ: TDPA on
both, the slave's passivity controller in the mapping); the
tissue force stays within the site's tissue limit (no tip-force DEGRADED or HOLD); and the
master–slave position drift TDPA leaves, which is reported (printed and written beside the logs;
with ``TELESURG_PERF_DIR=docs/data/perf`` also to ``haptics-two-hosts.json`` there, for
docs/haptics.md). The watchdog's holds are listed with their causes; the operator's script runs on
the engaged time (a hold pauses it), so the press is analysed on that clock.
"""

from __future__ import annotations

import json
import os
import re
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_two_hosts import (
    REPO,
    SITE,
    SLAVE_ADDR,
    TwoHosts,
    _log_tail,
    needs_two_hosts,
    two_hosts,
)

pytestmark = [pytest.mark.process, pytest.mark.timeout(300)]

SCALE = 1.0  # the mapping's scale here: the tissue is 40 mm below the tip's home (a Touch's reach at 1:1)
FORCE_SCALE = 0.5  # master force per slave contact force (haptics.force_scale default)
TISSUE_LIMIT_N = 4.0  # the watchdog's tip_force limit (default)
DELAY_MS = 50.0  # each way
SCRIPT_S = 7.3  # the touch_sim script's length while engaged (press_and_slide)
SLIDE_MM = 20.0
#: mm the operator means to press beyond the surface: a firm press well inside the tissue limit
#: (the bench's 11 mm gives ~2.4 N steady at 0.4 N/mm, and the slide on the crest reaches 4 N)
PRESS_MM = 6.0
#: Hz: the console's pose stream (its haptic loop stays at 1 kHz on the console host): 4 ms
#: against the link's 50 ms, and half the default's traffic through the TLS link and the impairer
MASTER_HZ = 250.0
#: s of script time: the press's hold (touch_sim.model.press_and_slide: press ends 2.3, slide starts 3.8)
PRESS_HOLD_S = (2.3, 3.8)


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


def _console(h: TwoHosts, surface_mm: float) -> None:
    argv = [str(REPO / "deploy" / "console.sh"), SLAVE_ADDR, "--no-console", "--site", SITE]
    argv += ["--certs", str(h.certs), "--log-dir", str(h.logs / "console")]
    for item in (
        'device="touch_sim"',
        'device_options.operator="site"',
        f"device_options.surface_mm={surface_mm:.1f}",
        f"device_options.slide_mm={SLIDE_MM}",
        f"device_options.press_mm={PRESS_MM}",
        'haptics.slave_arm="arm1"',
        'haptics.controller="tdpa"',
        f"haptics.force_scale={FORCE_SCALE}",
        f"rate_hz={MASTER_HZ:g}",
    ):
        argv += ["--set", f"master_capture.{item}"]
    h.spawn("console", h.console, argv)


def _hf_rms(t: np.ndarray, f: np.ndarray) -> float:
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


def analyse(recs: list[dict[str, Any]], t_follow: int) -> dict[str, Any]:
    """The figures of one press and slide from the probe's records (monotonic ns ``t``), phased by
    the operator's script clock (a hold mid-press pauses the script, so each phase keeps its
    engaged length): the steady force is the median over the press's last 0.5 s of holding."""
    cf = [(r["t"], *r["f"]) for r in recs if r["k"] == "cf" and r["t"] >= t_follow]
    mp = [(r["t"], *r["p"], r["e"]) for r in recs if r["k"] == "mp" and r["t"] >= t_follow]
    tip = [(r["t"], *r["p"]) for r in recs if r["k"] == "tip"]
    c, m, p = np.array(cf, dtype=float), np.array(mp, dtype=float), np.array(tip, dtype=float)
    tc, fz, fn = c[:, 0] / 1e9, c[:, 3], np.linalg.norm(c[:, 1:4], axis=1)
    mz, energy = m[:, 3], m[:, 4]
    clock_t, clock_s = script_clock(recs, t_follow)
    sc = np.interp(tc, clock_t, clock_s)  # each contact-force sample's script time
    # the press's hold: script 2.3-3.8 s (touch_sim.model.press_and_slide); its last 0.5 s,
    # a one-way delay after the master's, are the steady contact
    delay_s = DELAY_MS / 1e3
    settled = (sc >= PRESS_HOLD_S[1] - 0.5 + delay_s) & (sc <= PRESS_HOLD_S[1] + delay_s)
    assert settled.sum() >= 10, f"too few contact samples in the press's hold: {int(settled.sum())}"
    steady = float(np.median(fz[settled]))
    pressing = sc <= PRESS_HOLD_S[1] + delay_s  # reach, press and its hold
    overshoot = float(fz[pressing].max() / steady) if steady > 0 else float("inf")
    # drift: where the slave went against where the master (× scale) went, after the release
    home = p[p[:, 0] < t_follow][-1, 1:4] if (p[:, 0] < t_follow).any() else p[0, 1:4]
    end_t = p[-1, 0]
    slave_end = p[-1, 1:4]
    master_end = m[m[:, 0] <= end_t][-1, 1:4]
    drift = slave_end - (home + SCALE * (master_end - m[0, 1:4]))
    return {
        "steady_force_n": round(steady, 3),
        "overshoot": round(overshoot, 3),
        "hold_oscillation_rms_n": round(_hf_rms(tc[settled], fz[settled]), 4),
        "largest_force_n": round(float(fn.max()), 3),
        "master_energy_min_mj": round(float(energy.min()) * 1e3, 3),
        "master_energy_end_mj": round(float(energy[-1]) * 1e3, 3),
        "press_mm_master": round((float(m[0, 3]) - float(mz.min())) * 1e3, 2),
        "drift_mm": [round(float(v) * 1e3, 2) for v in drift],
        "drift_norm_mm": round(float(np.linalg.norm(drift)) * 1e3, 2),
        "engaged_s": round(float(clock_s[-1]), 2),
        "samples": {"cf": len(c), "mp": len(m), "tip": len(p)},
    }


def test_press_and_slide_on_the_tissue_across_two_hosts_with_tdpa(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    needs_two_hosts()
    tmp = tmp_path_factory.mktemp("haptics_two_hosts")
    site_flags = [
        "--set",
        f"mapping.scale={SCALE}",
        "--set",
        f"watchdog.rules.tip_force.limit_n={TISSUE_LIMIT_N}",
    ]
    # the link's own 50 ms each way is within the site's budget: a load peak on this 2-core VM
    # must not scale the motion down mid-press
    site_flags += ["--set", "watchdog.latency_budget_ms=150"]
    # TDPA on both ports: the slave's passivity controller in the mapping
    site_flags += [
        "--set",
        "mapping.slave_passivity=true",
        "--set",
        f"mapping.haptics_force_scale={FORCE_SCALE}",
    ]
    with two_hosts(tmp, site_flags=site_flags, probe_flags=["--haptics"]) as h:
        assert h.impair(f"delay {DELAY_MS:g}").startswith("ok"), "the impairer did not take the delay"
        home = h.probe.wait("tip", lambda r: True, timeout=20.0)
        assert home is not None, f"no slave tip from the site\n{_log_tail(h.logs)}"
        # where the console's operator expects the tissue, in the master's frame (below the start)
        surface_mm = (tissue_top_z() - home["p"][2]) / SCALE * 1e3
        _console(h, surface_mm)
        follow = h.probe.wait("op", lambda r: r["follow"], timeout=90.0)
        assert follow is not None, f"the slave never followed the haptic master\n{_log_tail(h.logs)}"
        # the script plays while engaged: wait for it to end (a hold pauses it), then a second more
        deadline = time.monotonic() + 60.0
        engaged_s = 0.0
        while engaged_s < SCRIPT_S + 1.0 and time.monotonic() < deadline:
            time.sleep(0.25)
            if h.probe.following():
                engaged_s += 0.25
        assert engaged_s >= SCRIPT_S + 1.0, f"engaged only {engaged_s:.1f} s in 60 s\n{_log_tail(h.logs)}"
        assert h.stop("console", signal.SIGTERM) == 0, _log_tail(h.logs)
        with h.probe.lock:
            recs = list(h.probe.recs)
    safety = [r for r in recs if r["k"] == "safety" and r["t"] >= follow["t"]]
    tissue = [r for r in safety if any("tip force" in c for c in r["causes"])]
    figures = analyse(recs, follow["t"])
    # the slave port (the mapping says at exit what its passivity controller saw and did)
    spc = re.search(
        r"slave passivity: observed W_s min (\S+) mJ, dissipated (\S+) mJ, drift max (\S+) mm",
        (h.logs / "slave" / "mapping.log").read_text(),
    )
    assert spc is not None, f"the mapping said nothing of its slave passivity controller\n{_log_tail(h.logs)}"
    figures["slave_energy_min_mj"], figures["slave_dissipated_mj"], figures["slave_drift_max_mm"] = (
        float(v) for v in spc.groups()
    )
    figures["surface_mm_master"] = round(surface_mm, 1)
    figures["delay_ms_each_way"] = DELAY_MS
    figures["tissue_states"] = sorted({r["state"] for r in tissue})
    figures["states"] = sorted({r["state"] for r in safety})
    figures["holds"] = [
        (round((r["t"] - follow["t"]) / 1e9, 2), r["state"], r["causes"])
        for r in safety
        if r["state"] != "OK"
    ][:10]
    (Path(tmp) / "records.json").write_text(json.dumps(recs))
    if out := os.environ.get("TELESURG_PERF_DIR"):  # docs/haptics.md's figures
        (Path(out) / "haptics-two-hosts.json").write_text(json.dumps(figures, indent=2) + "\n")
    (Path(tmp) / "haptics_two_hosts.json").write_text(json.dumps(figures, indent=2))
    print(json.dumps(figures, indent=2))

    assert figures["steady_force_n"] > 0.3, "the instrument never pressed the tissue"
    assert figures["overshoot"] <= 1.5, figures  # stable: no contact-force overshoot
    assert figures["hold_oscillation_rms_n"] < 0.1, figures  # and no sustained oscillation
    assert figures["master_energy_min_mj"] >= -1.0, figures  # the master port stays passive
    assert figures["slave_energy_min_mj"] >= -1.0, figures  # and so does the slave port
    assert figures["largest_force_n"] < TISSUE_LIMIT_N, figures  # within the tissue limit
    assert not tissue, f"the tissue limit was reached: {tissue[:3]}"
