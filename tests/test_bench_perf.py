"""Smoke runs of the performance benches (issue #9): each prints its table and writes its JSON.
No time is asserted here — the figures and the goals are in docs/performance.md."""

from __future__ import annotations

import calendar
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from telesurg.tools.bench import schedtrace


def bench(tmp_path: Path, *args: str) -> dict:  # type: ignore[type-arg]
    out = tmp_path / f"{args[0]}.json"
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.services.cli", "bench", *args, "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    print(r.stdout, r.stderr[-2000:])
    assert r.returncode == 0, r.stderr[-2000:]
    data: dict = json.loads(out.read_text())  # type: ignore[type-arg]
    return data


@pytest.mark.slow
def test_bench_sim_and_ik(tmp_path: Path) -> None:
    sim = bench(tmp_path, "sim", "--seconds", "0.3")
    assert set(sim) >= {"mh3f", "plas", "vip"} and all(
        sim[m]["steps_per_s"] > 0 for m in ("mh3f", "plas", "vip")
    )
    ik = bench(tmp_path, "ik", "--n", "30")
    assert ik["trocar_ik"]["rcm_err_max_m"] < 1e-9 and ik["trocar_ik"]["pos_err_max_m"] < 1e-9
    for k in ("ik_6axis", "vip_ik", "plas_map_step"):
        assert ik[k]["us_per_call"] > 0
    # the vectorised solvers solve every target, as exactly as the scalar one
    assert ik["trocar_ik"]["batch_all_solved"] and ik["trocar_ik"]["batch_rcm_err_max_m"] < 1e-9
    assert ik["trocar_ik"]["batch_solves_per_s"] > 0 and ik["ik_6axis"]["batch_solves_per_s"] > 0


@pytest.mark.slow
def test_bench_decode(tmp_path: Path) -> None:
    dec = bench(tmp_path, "decode", "--n", "200", "--repeat", "2")
    rows = dec["messages"]
    assert {r["type"] for r in rows.values()} >= {"servo_jp", "pose", "lease", "joint_state"}
    assert all(r["decode_us"] > 0 and r["encode_us"] > 0 and r["bytes"] > 0 for r in rows.values())
    # the machine it ran on, booted when /proc/uptime says: figures from another boot (another
    # host, however alike) are told apart by it
    uptime_s = float(Path("/proc/uptime").read_text().split()[0])
    booted = calendar.timegm(time.strptime(dec["machine"]["booted"], "%Y-%m-%d %H:%M:%S UTC"))
    assert abs(time.time() - uptime_s - booted) < 5, (dec["machine"], uptime_s)
    assert dec["machine"]["cpus"] == os.cpu_count() and dec["machine"]["kernel"] == os.uname().release
    assert dec["machine"]["cpu_model"] and dec["date"].endswith(" UTC")


def _hogs_left() -> list[int]:
    import psutil

    return [
        p.pid
        for p in psutil.process_iter(["cmdline"])
        if p.info["cmdline"] and p.info["cmdline"][-2:] == ["-c", "while True: pass"]
    ]


def test_load_specs() -> None:
    from telesurg.tools.bench.load import Load

    assert Load.parse("cpu:2") == Load("cpu", 2) and Load.parse("record").name == "record"
    bad_specs = (
        ("gpu", "valid: cpu:N, idle:N, record, stalled, viewer"),
        ("cpu:0", "1..16"),
        ("record:3", "no argument"),
    )
    for bad, why in bad_specs:
        with pytest.raises(ValueError, match=why):
            Load.parse(bad)
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.services.cli", "bench", "latency", "--load", "gpu"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "unknown kind" in r.stderr


@pytest.mark.process
def test_bench_latency_and_soak(tmp_path: Path) -> None:
    keep = tmp_path / "kept"
    lat = bench(
        tmp_path,
        "latency",
        "--rate",
        "250",
        "--seconds",
        "2",
        "--blocks",
        "1",
        "--load",
        "cpu:1",
        "--keep-logs",
        str(keep),
    )
    # --keep-logs: every block's service logs stay, e.g. the watchdog's transitions of the idle one
    assert "safety_transition" in (keep / "logs1" / "watchdog.log").read_text()
    assert lat["relay"]["end_to_end"]["n"] > 300 and lat["pipeline"]["end_to_end"]["n"] > 200
    assert lat["ratio_p50"] > 0
    # every stage of the setpoints the slave used, from the mapping's and the slave's logs
    stages = lat["stages"]
    assert stages["mapping_work"]["n"] > 200 and stages["slave_used_to_stepped"]["n"] > 200
    assert stages["end_to_end_used"]["p50"] == lat["pipeline"]["end_to_end"]["p50"]
    # the same run under one busy process: its own figures beside the idle ones, and the hog gone
    loaded = lat["loaded"]["cpu:1"]
    assert loaded["pipeline"]["end_to_end"]["n"] > 200 and loaded["pipeline_p99_vs_idle"] > 0
    # each HOLD with the watchdog's causes, so a hold in a latency run can be explained
    assert len(loaded["pipeline_watchdog_hold_causes"]) == loaded["pipeline_watchdog_holds"]
    assert isinstance(loaded["pipeline_startup_hold_causes"], list)  # (reported apart)
    # the kernel's scheduler slice unless $TELESURG_CONTROL_SLICE_US asks for one
    assert set(lat["pipeline_slice_threads"].values()) == {"-"}, lat["pipeline_slice_threads"]
    # and the ratio block by block (one block each here), beside the whole run's
    (block,) = loaded["pipeline_block_p99_vs_idle"]
    assert block == pytest.approx(loaded["pipeline_p99_vs_idle"], rel=0.05)
    assert not _hogs_left()
    soak = bench(tmp_path, "soak", "--rate", "250", "--seconds", "3")
    assert soak["streams"]["master/m1/measured_cp"]["messages"] > 500
    assert set(soak["cpu_pct"]) >= {"slave_control", "mapping", "watchdog", "master_capture"}
    assert soak["recorder"]["cpu_pct"] > 0  # the recorder's own load is reported, not in the total
    # the deploy configs run one loop thread of each of these under SCHED_FIFO (where permitted)
    rt = 1 if os.geteuid() == 0 else 0
    assert {n: soak["fifo_threads"][n] for n in ("master_capture", "mapping", "slave_control")} == {
        "master_capture": rt,
        "mapping": rt,
        "slave_control": rt,
    }
    assert soak["fifo_threads"]["watchdog"] == soak["fifo_threads"]["router"] == 0
    bare = bench(tmp_path, "soak", "--rate", "250", "--seconds", "3", "--no-record", "--rt-priority", "0")
    assert bare["recorder"] is None and bare["streams"] == {}
    assert set(bare["deadline_misses"]) == {"slave_control", "master_capture"}
    assert sum(bare["fifo_threads"].values()) == 0  # --rt-priority 0: the normal scheduler
    r = subprocess.run(  # a kept directory is never mixed with another run's
        [sys.executable, "-m", "telesurg.services.cli", "bench", "soak", "--keep-logs", str(keep)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "new or empty directory" in r.stderr, r.stderr


@pytest.mark.process
@pytest.mark.skipif(bool(schedtrace.unavailable()), reason=schedtrace.unavailable() or "-")
def test_bench_latency_traces_the_scheduler(tmp_path: Path) -> None:
    keep = tmp_path / "kept"
    lat = bench(
        tmp_path,
        *("latency", "--rate", "250", "--seconds", "2", "--blocks", "2", "--load", "cpu:2"),
        *("--sched-trace", "--keep-logs", str(keep)),
    )
    services = {"router", "watchdog", "slave_control", "mapping", "master_capture"}
    for figs in (lat["pipeline_sched_delay_ms"], lat["loaded"]["cpu:2"]["pipeline_sched_delay_ms"]):
        assert set(figs) == services, figs
        for svc, f in figs.items():
            # every control thread wakes and runs hundreds of times in 2 s at 250 Hz
            assert f["n"] > 100 and f["cpu_ms"] > 0, (svc, f)
            assert 0 <= f["p50"] <= f["p99"] <= f["p99_9"] <= f["max"], (svc, f)
    # the first block of each condition is traced (kept with --keep-logs), the second is not
    assert sorted(p.name for p in keep.glob("sched*.data")) == ["sched1.data", "sched2.data"]


def test_sched_trace_without_perf_is_refused(tmp_path: Path) -> None:
    bare = tmp_path / "bin"
    bare.mkdir()  # a PATH with nothing on it (python is started by its full path)
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.services.cli", "bench", "latency", "--sched-trace"],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PATH": str(bare)},
    )
    assert r.returncode == 2 and "--sched-trace: no perf" in r.stderr, r.stderr


def test_watchdog_holds_counts_the_runs_holds_not_the_stop_sequences() -> None:
    from telesurg.tools.bench.perf import watchdog_holds

    log = (
        "2026-12-02 04:45:48,119 watchdog INFO telesurg.shared.bus: [arm1] safety_transition: HOLD → OK\n"
        "2026-12-02 04:45:50,002 watchdog ERROR telesurg.shared.bus: [arm1] safety_transition: "
        "OK → HOLD: master measured_cp stale (93 ms)\n"
        "2026-12-02 04:45:50,500 watchdog INFO telesurg.shared.bus: [arm1] safety_transition: HOLD → OK\n"
        "2026-12-02 04:45:51,000 watchdog WARNING telesurg.shared.bus: [arm1] safety_transition: "
        "OK → DEGRADED: x\n"
        "2026-12-02 04:45:52,011 watchdog ERROR telesurg.shared.bus: [arm1] safety_transition: "
        "DEGRADED → HOLD: master_capture not alive\n"
    )
    stop = time.mktime(time.strptime("2026-12-02 04:45:52", "%Y-%m-%d %H:%M:%S"))
    assert watchdog_holds(log) == ["master measured_cp stale (93 ms)", "master_capture not alive"]
    assert watchdog_holds(log, until=stop) == ["master measured_cp stale (93 ms)"]
    # a HOLD before the measured window (the services still starting) is not the window's
    begin = time.mktime(time.strptime("2026-12-02 04:45:51", "%Y-%m-%d %H:%M:%S"))
    assert watchdog_holds(log, until=stop, since=begin) == []
    assert watchdog_holds(log, since=begin) == ["master_capture not alive"]


def test_the_stages_join_each_setpoint_across_the_logs() -> None:
    """A setpoint's row takes the mapping's and the tap's times by its servo_jp stamp; a setpoint
    one log lacks keeps 0 there (and that stage leaves it out)."""
    from telesurg.tools.bench.perf import STAGE_COLUMNS, _stage_figures, _stages

    # the slave's log: origin, servo_jp stamp, used, stepped, reference played (ns)
    slave = np.array([[100, 300, 900, 950, 50], [200, 400, 1000, 1100, 0]], dtype=np.int64)
    mapping = np.array([[200, 250, 260, 400], [100, 150, 160, 300]], dtype=np.int64)  # (unsorted)
    tap = np.array([[300, 600]], dtype=np.int64)  # the second setpoint never reached the tap
    rows = _stages(slave, mapping, tap)
    col = {c: i for i, c in enumerate(STAGE_COLUMNS)}
    assert rows[:, col["mapping_received"]].tolist() == [150, 250]
    assert rows[:, col["mapping_began"]].tolist() == [160, 260]
    assert rows[:, col["tap_received"]].tolist() == [600, 0]
    assert rows[:, col["slave_stepped"]].tolist() == [950, 1100]
    figs = _stage_figures(rows)
    assert figs["servo_jp_to_tap"]["n"] == 1 and figs["servo_jp_to_tap"]["p50"] == 300 / 1e6
    assert figs["reference_lag"]["n"] == 1 and figs["reference_lag"]["p50"] == 900 / 1e6
    assert figs["end_to_end_used"]["n"] == 2


@pytest.mark.slow
def test_bench_wakeup(tmp_path: Path) -> None:
    from telesurg.shared.timing import fair_slice_us

    res = bench(
        tmp_path, "wakeup", "--seconds", "0.5", "--blocks", "1", "--load", "cpu:1", "--slice-us", "200"
    )
    for load in ("idle", "cpu:1"):
        kernel, asked = res["lateness_us"][load]["kernel"], res["lateness_us"][load]["asked"]
        assert kernel["n"] > 100 and asked["n"] > 100  # ~one wake-up a ms for 0.5 s each
        assert asked["p99"] >= asked["p50"] >= 0
        # the probe read its own slice back: the kernel's in one block, the one asked for in the
        # other where the kernel takes one (Linux ≥ 6.12; else the kernel's again)
        assert kernel["slice_us"] == fair_slice_us()
        assert asked["slice_us"] in (200.0, fair_slice_us())
    assert not _hogs_left()


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (["--slice-us", "50"], "100..100000"),
        (["--load", "record"], "cpu:N or idle:N"),
        (["--slice-us", "0"], "kernel"),
    ],
)
def test_bench_wakeup_refuses_what_it_cannot_measure(args: list[str], why: str) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.services.cli", "bench", "wakeup", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and why in r.stderr, r.stderr


@pytest.mark.slow
def test_busy_processes_end_with_a_bench_that_is_killed(tmp_path: Path) -> None:
    import psutil

    code = (
        "import sys, time\n"
        "from pathlib import Path\n"
        "from telesurg.tools.bench.load import Load\n"
        "with Load.parse('cpu:2').running('', Path(sys.argv[1])) as pids:\n"
        "    print(*pids, flush=True)\n"
        "    time.sleep(60)\n"
    )
    bench_proc = subprocess.Popen(
        [sys.executable, "-c", code, str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    assert bench_proc.stdout is not None
    pids = [int(p) for p in bench_proc.stdout.readline().split()]
    assert len(pids) == 2 and all(psutil.pid_exists(p) for p in pids)
    bench_proc.terminate()  # SIGTERM: no clean-up of its own runs
    bench_proc.wait(10)
    bench_proc.stdout.close()
    _gone, alive = psutil.wait_procs([psutil.Process(p) for p in pids if psutil.pid_exists(p)], timeout=10)
    for p in alive:  # (the test's own processes: ended, and then the failure reported)
        p.kill()
    assert not alive, f"busy processes left after the bench ended: {alive}"
    assert not _hogs_left()
