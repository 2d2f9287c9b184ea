"""Link profiles on real packets: a PacketLink between two network namespaces, UDP datagrams across.

A sender in namespace A stamps every datagram (``tools/bench/udpflow.py``), a receiver in B
records it; both read CLOCK_MONOTONIC, which namespaces share, so each row is a one-way delay.
Checked: the delay distribution of a profile with jitter (mean within 1 ms, the spread as set),
order kept under jitter and broken only when reordering is asked, random loss within 4 σ over
3,000 datagrams, bursty loss with the configured mean burst (±30 %), the bandwidth cap (throughput
within 10 %), an outage (everything sent during it lost, nothing else).

Root only (namespaces, TUN devices): skips with the reason otherwise.
"""

from __future__ import annotations

import itertools
import math
import os
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from telesurg.tools.bench.impair import NetNamespace, PacketLink, netns_available
from telesurg.tools.bench.netprofile import LinkProfile, profile
from telesurg.tools.bench.udpflow import IP_UDP_OVERHEAD

pytestmark = [pytest.mark.process, pytest.mark.timeout(60)]

REPO = Path(__file__).resolve().parents[1]
ADDR_A, ADDR_B = "10.253.0.1", "10.253.0.2"
PORT = 9000
_PORTS = itertools.count(PORT)


class Flow:
    """Two namespaces and the link between them; :meth:`run` sends one flow and returns the rows."""

    def __init__(self, a: NetNamespace, b: NetNamespace, link: PacketLink, tmp: Path) -> None:
        self.a, self.b, self.link, self.tmp = a, b, link, tmp
        self.env = dict(os.environ, PYTHONPATH=str(REPO))

    def run(self, count: int, interval_ms: float, size: int = 64) -> np.ndarray:
        """Rows (seq, sent ns, received ns, bytes) in arrival order."""
        port = next(_PORTS)
        out = self.tmp / f"rows-{port}.npy"
        me = [sys.executable, "-m", "telesurg.tools.bench.udpflow"]
        opts = ["--interval-ms", f"{interval_ms:g}", "--size", str(size)]
        recv = subprocess.Popen(
            self.b.cmd([*me, "recv", ADDR_B, str(port), "--out", str(out), "--idle-s", "0.5"]),
            stdout=subprocess.PIPE,
            text=True,
            env=self.env,
        )
        try:
            assert recv.stdout is not None
            assert recv.stdout.readline().strip() == "ready"
            subprocess.run(
                self.a.cmd([*me, "send", ADDR_B, str(port), "--count", str(count), *opts]),
                env=self.env,
                check=True,
                capture_output=True,
                timeout=30,
            )
            assert recv.wait(30) == 0
        finally:
            if recv.poll() is None:
                recv.kill()
                recv.wait()
            if recv.stdout is not None:
                recv.stdout.close()
        return np.load(out)


@pytest.fixture(scope="module")
def flow(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Flow]:
    if why := netns_available():
        pytest.skip(f"link profiles on real packets {why}")
    tag = os.getpid() % 100000
    with (
        NetNamespace(f"tsnp-a-{tag}") as a,
        NetNamespace(f"tsnp-b-{tag}") as b,
        PacketLink(a.name, b.name, addr_a=ADDR_A, addr_b=ADDR_B, name=f"tsnp{tag}", seed=11) as link,
    ):
        yield Flow(a, b, link, tmp_path_factory.mktemp("flows"))


def one_way_ms(rows: np.ndarray) -> np.ndarray:
    return (rows[:, 2] - rows[:, 1]) / 1e6


def test_delay_and_jitter_match_the_lindbergh_profile(flow: Flow) -> None:
    """75 ms ± 10 ms uniform: mean within 1 ms, σ of a uniform ±10 ms (5.77 ms) within 15 %."""
    prof = profile("lindbergh")
    flow.link.set_profile(prof)
    rows = flow.run(300, interval_ms=21)  # spaced wider than the jitter: no packet waits for another
    d = one_way_ms(rows)
    assert len(rows) == 300
    sigma = prof.jitter_ms / math.sqrt(3)
    print(
        f"one-way {d.mean():.2f} ms mean, σ {d.std():.2f} ms (uniform: {sigma:.2f}), "
        f"{d.min():.1f}..{d.max():.1f}"
    )
    assert abs(d.mean() - prof.delay_ms) < 1.0
    assert abs(d.std() - sigma) < 0.15 * sigma
    assert d.min() >= prof.delay_ms - prof.jitter_ms - 0.2
    assert d.max() <= prof.delay_ms + prof.jitter_ms + 5.0  # + the host's scheduling


def test_jitter_keeps_order_and_reordering_breaks_it(flow: Flow) -> None:
    """Dense datagrams under ±10 ms of jitter arrive in order; with 10 % reordering ~10 % do not."""
    flow.link.set_profile(LinkProfile(delay_ms=20, jitter_ms=10))
    rows = flow.run(1000, interval_ms=1)
    assert len(rows) == 1000
    assert (np.diff(rows[:, 0]) > 0).all(), "a datagram overtook another without reordering asked"
    flow.link.set_profile(LinkProfile(delay_ms=20, jitter_ms=10, reorder=0.1, reorder_ms=15))
    rows = flow.run(1000, interval_ms=1)
    assert len(rows) == 1000
    late = int((rows[:, 0] < np.maximum.accumulate(rows[:, 0])).sum())  # arrived after a later one
    print(f"reordered: {late} of 1000")
    assert 60 <= late <= 140


def test_random_loss_of_the_5g_profile(flow: Flow) -> None:
    """1.2 % independent loss over 3,000 datagrams: within 4 σ of 36."""
    prof = profile("5g-microhand")
    flow.link.set_profile(prof)
    n = 3000
    rows = flow.run(n, interval_ms=0.7)
    lost = n - len(np.unique(rows[:, 0]))
    sd = math.sqrt(n * prof.loss * (1 - prof.loss))
    print(f"lost {lost} of {n} (expected {n * prof.loss:.0f} ± {sd:.1f})")
    assert abs(lost - n * prof.loss) <= 4 * sd
    assert abs(one_way_ms(rows).mean() - prof.delay_ms) < 1.0


def _bursts(rows: np.ndarray, n: int) -> list[int]:
    got = np.zeros(n, dtype=bool)
    got[rows[:, 0]] = True
    runs, cur = [], 0
    for ok in got:
        if not ok:
            cur += 1
        elif cur:
            runs.append(cur)
            cur = 0
    return runs + ([cur] if cur else [])


def test_bursty_loss_has_the_configured_mean_burst(flow: Flow) -> None:
    """Gilbert–Elliott 5 % loss in bursts of 4: mean burst 4 ± 30 %, mean loss 5 % ± 40 %;
    independent 5 % loss: bursts near 1."""
    n = 6000
    flow.link.set_profile(LinkProfile(delay_ms=5, loss=0.05, burst=4))
    runs = _bursts(flow.run(n, interval_ms=0.5), n)
    mean_burst, loss = sum(runs) / len(runs), sum(runs) / n
    flow.link.set_profile(LinkProfile(delay_ms=5, loss=0.05))
    indep = _bursts(flow.run(n, interval_ms=0.5), n)
    print(
        f"bursty: {len(runs)} bursts, mean {mean_burst:.2f}, loss {100 * loss:.2f} %; "
        f"independent: mean burst {sum(indep) / len(indep):.2f}"
    )
    assert abs(mean_burst - 4) <= 0.3 * 4
    assert abs(loss - 0.05) <= 0.4 * 0.05
    assert sum(indep) / len(indep) < 1.3


def test_bandwidth_cap_holds_and_its_queue_drops(flow: Flow) -> None:
    """2 Mbit/s cap, 4 Mbit/s offered: delivered within 10 % of 2 Mbit/s, the excess dropped."""
    flow.link.set_profile(LinkProfile(delay_ms=5, rate_kbps=2000, queue=50))
    before = dict(flow.link.counts)
    size = 1000
    rows = flow.run(1000, interval_ms=2, size=size)  # 500/s × 1,028 IP bytes ≈ 4.1 Mbit/s for 2 s
    span_s = (rows[-1, 2] - rows[0, 2]) / 1e9
    kbps = (len(rows) - 1) * (size + IP_UDP_OVERHEAD) * 8 / span_s / 1000
    dropped = flow.link.counts["queue"] - before["queue"]
    print(
        f"delivered {kbps:.0f} kbit/s of 2000, {len(rows)} of 1000, queue drops {dropped}, "
        f"one-way max {one_way_ms(rows).max():.0f} ms"
    )
    assert abs(kbps - 2000) <= 0.1 * 2000
    assert dropped > 300
    assert one_way_ms(rows).max() < 5 + 50 * 1028 * 8 / 2000 + 20  # queue of 50 drained at the cap


def test_an_outage_drops_everything_for_its_length(flow: Flow) -> None:
    """300 ms outages every 1.5 s: each gap in the received datagrams spans 300 ms of sends
    (1 ms apart), and nothing else is lost."""
    flow.link.set_profile(replace(LinkProfile(delay_ms=5), outage_ms=300, outage_every_s=1.5))
    before = dict(flow.link.counts)
    rows = flow.run(2500, interval_ms=1)
    seqs = np.sort(rows[:, 0])
    sent = dict(zip(rows[:, 0].tolist(), rows[:, 1].tolist(), strict=True))
    gaps = [(sent[int(b)] - sent[int(a)]) / 1e6 for a, b in itertools.pairwise(seqs.tolist()) if b - a > 1]
    outage = flow.link.counts["outage"] - before["outage"]
    print(f"outage: sends {[round(g, 1) for g in gaps]} ms apart across the gaps; {outage} dropped")
    assert gaps, "no outage seen"
    assert all(300 <= g <= 315 for g in gaps), gaps
    assert flow.link.counts["lost"] == before["lost"] and flow.link.counts["queue"] == before["queue"]
    assert 2500 - len(rows) == outage  # every datagram not delivered was dropped by an outage
