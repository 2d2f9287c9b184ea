"""Property-based fuzzing of the *running* services (hypothesis → zenoh → real processes).

Hypothesis builds batches of payloads — arbitrary bytes, and valid messages mutated by
:func:`telesurg.tools.bench.fuzzgen.mutate` — and publishes them on every key the services
subscribe to, while the scripted master drives the MuJoCo slave. Afterwards: every service is still
alive, each one's rejection counter (from its heartbeat) equals what the same strict decoder and
source rules say it must reject, the slave never left its joint limits, and it follows the master
again.
"""

from __future__ import annotations

import random
import time
from collections import Counter
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from telesurg.shared.auth import PUT
from telesurg.shared.robots.mh3f.kinematics import MH3F
from telesurg.tools.bench.fuzz import (
    ROUTER_CAP,
    SERVICES,
    TARGETS,
    counts_match,
    expected_rejections,
    fuzz_signer,
    rejections,
)
from telesurg.tools.bench.fuzzgen import mutate, valid_template
from telesurg.tools.bench.harness import Pipeline

pytestmark = pytest.mark.process

KEYS = sorted(TARGETS)


@pytest.fixture(scope="module")
def pipe(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pipeline]:
    logs = tmp_path_factory.mktemp("fuzz") / "logs"
    with Pipeline(logs, impair=False) as p:
        assert p.wait_following(30), "the slave never followed"
        yield p
    for f in sorted(logs.glob("*.log")):
        text = "\n".join(line for line in f.read_text().splitlines() if "rejected message" not in line)
        print(f"--- {f.name}\n{text[-2000:]}")


@st.composite
def payloads(draw: Any) -> tuple[str, bytes]:
    key = draw(st.sampled_from(KEYS))
    if draw(st.booleans()):
        return key, draw(st.binary(max_size=400))
    # Look-alikes from an untrusted source: their fate does not depend on stream state, so the
    # expected counts are exact. (Forged trusted sources: tests/test_streams_and_sources.py.)
    valid = valid_template(TARGETS[key][0], source="fuzz")
    _, payload = mutate(random.Random(draw(st.integers(0, 2**32))), valid.encode())
    return key, payload


def test_running_services_reject_count_and_never_move_the_slave_out_of_limits(pipe: Pipeline) -> None:
    import zenoh

    p = pipe.p
    prefix = pipe.node.keys.prefix
    signer = fuzz_signer(pipe.node)
    pubs = {
        k: pipe.node.session.declare_publisher(
            f"{prefix}/{k}", congestion_control=zenoh.CongestionControl.BLOCK
        )
        for k in KEYS
    }
    pipe.settled_heartbeats()  # every service caught up (a mirror's start-up backlog)
    before = pipe.tallies()
    expected: Counter[str] = Counter()
    sent = Counter[str]()
    at_router = Counter[str]()

    @settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    @given(batch=st.lists(payloads(), min_size=10, max_size=60))
    def throw(batch: list[tuple[str, bytes]]) -> None:
        for key, payload in batch:
            exp = expected_rejections(key, payload)
            if key == "estop" and exp["watchdog"] == 0:
                continue  # a decodable e-stop would (rightly) stop the arm
            # signed (as the fuzzer): the payloads pass authentication and meet the decoder
            attachment = signer.attach(PUT, f"{prefix}/{key}", payload)
            pubs[key].put(payload, attachment=attachment)
            sent[key] += 1
            if len(payload) + len(attachment) > ROUTER_CAP:
                at_router[key] += 1  # the router's size cap drops it: no service sees it
            else:
                expected.update(exp)
        time.sleep(0.005)

    throw()
    pipe.settled_heartbeats()
    assert pipe.site.dead() == {}, "a service died while fuzzed"
    got, lost = rejections(before, pipe.tallies())
    with p.lock:
        joints = np.array(p.joints, dtype=float)
    print(
        f"sent {sum(sent.values())} payloads: {dict(sent)}; dropped at the router (size cap) "
        f"{dict(at_router)}; rejected {got}; expected {dict(expected)}; lost {lost}"
    )
    assert sum(sent.values()) > 500
    assert counts_match(got, lost, {s: expected[s] for s in SERVICES}), (got, dict(expected), lost)
    lo, hi = np.array(MH3F.lower), np.array(MH3F.upper)
    assert joints.shape[0] > 100 and not ((joints < lo) | (joints > hi)).any()
    for pub in pubs.values():
        pub.undeclare()  # type: ignore[no-untyped-call]
    assert pipe.wait_following(15), "the slave did not follow again after the fuzzing"
