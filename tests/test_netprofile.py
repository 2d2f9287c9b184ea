"""Link profiles without root: the named table, bad values, the shared options, the per-packet model.

The model is pure (arrival times in, departure times or drop reasons out), so its statistics are
checked here on many packets; ``tests/test_netprofile_process.py`` checks the same on real
datagrams through a PacketLink (root).
"""

from __future__ import annotations

import argparse
import math
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from telesurg.shared.errors import ConfigError
from telesurg.tools.bench import transport
from telesurg.tools.bench.impair import LinkImpairer, control_command
from telesurg.tools.bench.netprofile import (
    PROFILES,
    LinkModel,
    LinkProfile,
    add_profile_args,
    profile,
    profile_from_args,
)

REPO = Path(__file__).resolve().parents[1]


def run(model: LinkModel, n: int, interval_s: float, size: int = 100) -> list[float | str]:
    return [model.admit(i * interval_s, size) for i in range(n)]


def bursts(out: list[float | str]) -> list[int]:
    runs, cur = [], 0
    for o in out:
        if o == "loss":
            cur += 1
        elif cur:
            runs.append(cur)
            cur = 0
    return runs + ([cur] if cur else [])


# ------------------------------------------------------------------ the table and its checks


def test_named_profiles_have_the_round_trips_of_their_sources() -> None:
    rtt = {name: 2 * p.delay_ms for name, p in PROFILES.items()}
    assert rtt == {
        "lan": pytest.approx(0.4),
        "fibre-30km": 27.0,
        "5g-microhand": 114.0,
        "intercontinental": 200.0,
        "lindbergh": 150.0,
    }
    assert PROFILES["5g-microhand"].loss == 0.012
    assert PROFILES["lindbergh"].jitter_ms == 10.0


@pytest.mark.parametrize(
    ("overrides", "says"),
    [
        ({"delay_ms": -1.0}, "delay_ms"),
        ({"loss": 1.0}, "loss must be in [0, 1)"),
        ({"burst": 0.5}, "burst"),
        ({"jitter_ms": math.nan}, "jitter_ms"),
        ({"jitter": "cauchy"}, "uniform or normal"),
        ({"outage_ms": 2000.0, "outage_every_s": 1.0}, "outage_every_s"),
        ({"colour": 1.0}, "valid: "),
    ],
)
def test_bad_values_raise_one_clear_error(overrides: dict[str, float], says: str) -> None:
    with pytest.raises(ConfigError, match=None) as err:
        profile("lan", **overrides)
    assert says in str(err.value)
    assert "\n" not in str(err.value)


def test_unknown_profile_names_the_valid_ones() -> None:
    with pytest.raises(ConfigError) as err:
        profile("mars")
    assert str(err.value) == f"unknown link profile 'mars'; valid: {', '.join(PROFILES)}"


def test_options_override_a_named_profile() -> None:
    ap = argparse.ArgumentParser()
    add_profile_args(ap)
    args = ap.parse_args(
        ["--profile", "5g-microhand", "--burst", "3", "--outage", "500/10", "--jitter-ms", "2"]
    )
    p = profile_from_args(args)
    assert (p.delay_ms, p.loss, p.burst, p.jitter_ms) == (57.0, 0.012, 3.0, 2.0)
    assert (p.outage_ms, p.outage_every_s) == (500.0, 10.0)
    assert profile_from_args(ap.parse_args([]), delay_default=10.0) == LinkProfile(delay_ms=10.0)
    with pytest.raises(ConfigError, match="--outage wants MS or MS/EVERY_S"):
        profile_from_args(ap.parse_args(["--outage", "soon"]))


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--profile", "mars"], "valid: lan, fibre-30km, 5g-microhand, intercontinental, lindbergh"),
        (["--delay-ms", "-5"], "delay_ms must be a finite number >= 0"),
        (["--loss", "1"], "loss must be in [0, 1)"),
    ],
)
def test_impair_cli_rejects_bad_values_in_one_line(argv: list[str], says: str) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "telesurg.tools.bench.impair", "--listen", "127.0.0.1:0", *argv],
        capture_output=True,
        text=True,
        timeout=20,
        cwd=REPO,
    )
    assert r.returncode == 2
    assert r.stdout == ""  # never listened
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("telesurg impair: ") and says in lines[0], r.stderr


# ------------------------------------------------------------------ the model


def test_jitter_keeps_fifo_order_and_the_floor() -> None:
    m = LinkModel(LinkProfile(delay_ms=20, jitter_ms=10), seed=1)
    out = run(m, 5000, 0.001)
    due = [float(o) for o in out]
    assert due == sorted(due)
    assert min(d - i * 0.001 for i, d in enumerate(due)) >= 0.010 - 1e-9


def test_sparse_jitter_is_uniform_with_the_set_mean_and_spread() -> None:
    m = LinkModel(PROFILES["lindbergh"], seed=2)
    n = 20000
    delays = [(float(o) - i * 0.05) * 1000 for i, o in enumerate(run(m, n, 0.05))]
    mean = sum(delays) / n
    sd = math.sqrt(sum((d - mean) ** 2 for d in delays) / n)
    assert abs(mean - 75.0) < 0.2
    assert abs(sd - 10 / math.sqrt(3)) < 0.1
    assert min(delays) >= 65.0 and max(delays) <= 85.0


def test_reordering_lets_a_fraction_arrive_after_later_packets() -> None:
    m = LinkModel(LinkProfile(delay_ms=10, reorder=0.1, reorder_ms=5), seed=3)
    due = [float(o) for o in run(m, 10000, 0.001)]
    late = sum(1 for i in range(len(due) - 1) if due[i] > due[i + 1])
    assert 800 <= late <= 1200


def test_same_seed_same_drops_and_times() -> None:
    p = LinkProfile(delay_ms=30, jitter_ms=5, loss=0.05, burst=3, reorder=0.02)
    assert run(LinkModel(p, seed=9), 3000, 0.001) == run(LinkModel(p, seed=9), 3000, 0.001)
    assert run(LinkModel(p, seed=9), 3000, 0.001) != run(LinkModel(p, seed=10), 3000, 0.001)


@pytest.mark.parametrize(("loss", "burst"), [(0.012, 1.0), (0.05, 4.0), (0.02, 10.0)])
def test_gilbert_elliott_gives_the_mean_loss_and_burst(loss: float, burst: float) -> None:
    n = 200_000
    out = run(LinkModel(LinkProfile(loss=loss, burst=burst), seed=4), n, 0.001)
    runs = bursts(out)
    assert abs(sum(runs) / n - loss) < 0.1 * loss
    assert abs(sum(runs) / len(runs) - burst) < 0.1 * burst


def test_token_bucket_caps_throughput_and_drops_beyond_the_queue() -> None:
    m = LinkModel(LinkProfile(rate_kbps=1000, queue=20), seed=5)
    out = run(m, 2000, 0.0005, size=1000)  # 16 Mbit/s offered to a 1 Mbit/s cap for 1 s
    sent = [float(o) for o in out if not isinstance(o, str)]
    assert out.count("queue") > 1800
    kbps = (len(sent) - 1) * 1000 * 8 / (sent[-1] - sent[0]) / 1000
    assert abs(kbps - 1000) < 30  # the bucket's 3,000 bytes pass at once: +24 kbit/s over this 1 s
    assert max(d - i * 0.0005 for i, d in enumerate(out) if not isinstance(d, str)) <= 21 * 0.008 + 1e-9


def test_outages_drop_everything_for_their_length_and_repeat() -> None:
    m = LinkModel(LinkProfile(outage_ms=250, outage_every_s=1.0), seed=6, start=0.0)
    out = run(m, 3000, 0.001)
    dropped = [i for i, o in enumerate(out) if o == "outage"]
    assert dropped == list(range(1000, 1250)) + list(range(2000, 2250))


def test_reconfigure_keeps_order() -> None:
    m = LinkModel(LinkProfile(delay_ms=100), seed=7)
    first = m.admit(0.0, 100)
    m.reconfigure(LinkProfile(delay_ms=0))
    assert m.admit(0.001, 100) == first  # a lower delay does not overtake the packet in flight


# ------------------------------------------------------------------ the TCP proxy


def test_link_impairer_applies_delay_jitter_not_loss() -> None:
    srv = socket.create_server(("127.0.0.1", 0))
    with LinkImpairer(srv.getsockname()[:2], seed=1) as link:
        applied = link.set_profile(profile("5g-microhand", delay_ms=20, jitter_ms=5))
        assert applied.loss == 0 and applied.jitter_ms == 5 and link.delay_ms == 20
        with socket.create_connection(link.address, timeout=3) as c:
            conn, _ = srv.accept()
            with conn:
                times = []
                for _ in range(10):
                    t0 = time.monotonic()
                    c.sendall(b"x")
                    assert conn.recv(1) == b"x"
                    times.append(time.monotonic() - t0)
    srv.close()
    assert min(times) >= 0.015  # 20 ms − 5 ms of jitter at least, one way


def test_gilbert_elliott_from_transition_probabilities() -> None:
    p = LinkProfile.from_transitions(0.01, 0.25)
    assert p.loss == pytest.approx(0.01 / 0.26) and p.burst == pytest.approx(4.0)
    assert (p.p_good_bad, p.p_bad_good) == (pytest.approx(0.01), pytest.approx(0.25))
    with pytest.raises(ConfigError):
        LinkProfile.from_transitions(0.0, 0.5)


def test_transport_bench_rejects_a_bad_profile_before_anything_runs(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert transport.main(["--profile", "mars"]) == 2
    assert transport.main(["--profile", "lan", "--loss", "0,1.5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"telesurg bench transport: unknown link profile 'mars'; valid: {', '.join(PROFILES)}",
        "telesurg bench transport: bad link profile: loss must be in [0, 1), got 1.5",
    ]


def test_control_command_applies_a_profile() -> None:
    srv = socket.create_server(("127.0.0.1", 0))
    with LinkImpairer(srv.getsockname()[:2]) as link:
        assert control_command(link, "profile fibre-30km") == "ok delay 13.5"
        assert control_command(link, "profile mars").startswith(
            "error unknown link profile 'mars'; valid: lan"
        )
        assert link.delay_ms == 13.5
    srv.close()
