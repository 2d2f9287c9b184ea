"""Issue #39, acceptance 1, with the real services (router, watchdog, slave_control on MuJoCo,
mapping, master_capture; the bench site of ``telesurg bench attack``, clutch released).

A stranger *without the keyring* (a plain zenoh session) captures genuine signed messages —
``servo_jp``, leases, master poses and buttons, the console's e-stop and its reset, and the
console's ``set_scale``, ``scale_up``, ``teach_trocar``, ``begin_posture_adjust`` and ``state``
queries — and sends them again 0.1 s, 1 s and 10 s later, once also after another identity's
e-stop, and once more after the mapping restarted. Every replay is refused and counted by the
services (heartbeat ``rejected``, ``replayed`` events naming the signer), every replayed query is
answered ``rejected: …``; the slave moves < 0.1 mm and the scale, the taught trocar and the e-stop
latch stay as the operator left them. A signed reply of an earlier query, offered as the answer
to the console's next ``state``, is not taken.
"""

from __future__ import annotations

import contextlib
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from telesurg.shared import auth
from telesurg.shared.bus import open_session
from telesurg.shared.messages import Command, CommandReply, Header, OperatingState, decode_as
from telesurg.tools.bench import attack
from telesurg.tools.bench.harness import now_ns

pytestmark = [pytest.mark.process, pytest.mark.timeout(600)]

#: captured puts kept per key (the newest)
KEEP = {"slave/arm1/servo_jp": 200, "safety/arm1/lease": 20, "master/m1/measured_cp": 100}
PUT_KEYS = ("slave/arm1/servo_jp", "safety/arm1/lease", "master/m1/measured_cp", "master/m1/buttons", "estop")
MOTION_LIMIT_MM = 0.1


class Stranger:
    """A zenoh client of the site without the keyring: records the puts on :data:`PUT_KEYS` and
    the queries on the command keys (it answers none of them), and sends them again."""

    def __init__(self, a: attack.Attacker) -> None:
        self.prefix = a.k.prefix
        self.session = open_session(a.pipe.spec.client_bus(attack.CREDENTIAL))
        self.lock = threading.Lock()
        self.puts: dict[str, list[tuple[bytes, bytes]]] = {k: [] for k in PUT_KEYS}
        self.queries: list[tuple[str, str, bytes, bytes]] = []  # (key, command name, payload, attachment)
        self.recording = True
        self._h = [self.session.declare_subscriber(f"{self.prefix}/{k}", self._on_put) for k in PUT_KEYS]
        for k in (a.k.command("arm1"), a.k.mapping_command("arm1")):
            self._h.append(self.session.declare_queryable(k, self._on_query))

    def _on_put(self, s: Any) -> None:
        rel = str(s.key_expr)[len(self.prefix) + 1 :]
        with self.lock:
            if self.recording and s.attachment is not None:
                got = self.puts[rel]
                got.append((s.payload.to_bytes(), s.attachment.to_bytes()))
                if rel in KEEP and len(got) > KEEP[rel]:
                    del got[0]

    def _on_query(self, q: Any) -> None:
        if q.payload is None or q.attachment is None:
            return
        body = q.payload.to_bytes()
        with self.lock:
            if self.recording:
                name = decode_as(body, Command).name
                self.queries.append((str(q.key_expr), name, body, q.attachment.to_bytes()))

    def replay(self, only_estop: bool = False) -> tuple[dict[str, int], list[str]]:
        """Send every captured put and query again; (puts sent per key, the queries' answers)."""
        with self.lock:
            puts = {k: list(v) for k, v in self.puts.items() if not only_estop or k == "estop"}
            queries = [] if only_estop else list(self.queries)
        for rel, items in puts.items():
            for payload, att in items:
                self.session.put(f"{self.prefix}/{rel}", payload, attachment=att)
        answers = []
        for key, name, body, att in queries:
            replies = list(self.session.get(key, payload=body, attachment=att, timeout=3.0))
            errs = [r.err.payload.to_string() for r in replies if r.err is not None]
            oks = [r for r in replies if r.ok is not None]
            answers.append(f"{name}: {'ACCEPTED' if oks else ''}{' | '.join(errs) or 'no answer'}")
        return {k: len(v) for k, v in puts.items()}, answers

    def close(self) -> None:
        for h in self._h:
            with contextlib.suppress(Exception):
                h.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]


def test_replayed_messages_and_commands_change_nothing(tmp_path: Path) -> None:
    with contextlib.ExitStack() as stack:
        a = attack.open_site(stack, tmp_path / "logs", quick=True)
        _replays(a, stack)


def _replays(a: attack.Attacker, stack: contextlib.ExitStack) -> None:
    pipe, k = a.pipe, a.k
    trocar: list[tuple[float, float, float]] = []
    a.node.subscribe(
        k.slave("arm1", "operating_state"),
        OperatingState,
        lambda m, key: trocar.append(m.trocar),
        sources=["slave_control"],
    )
    spy = Stranger(a)
    stack.callback(spy.close)
    time.sleep(0.5)
    sk, mk = k.command("arm1"), k.mapping_command("arm1")

    # -- the operator's genuine commands, e-stop and reset (the stranger records them) ----------
    assert a.request(mk, "console", "set_scale", "value=0.3")[0]
    assert pipe.wait(lambda: a.obs.scale() == 0.3, 5.0)
    assert a.request(mk, "console", "scale_up")[0]
    assert pipe.wait(lambda: a.obs.scale() == 0.5, 5.0)
    a.request(sk, "console", "teach_trocar")
    ok, reason, token = a.request(sk, "console", "begin_posture_adjust", "method=ptp")
    assert not ok and token, reason  # asked to confirm; never confirmed: nothing moves
    assert a.request(sk, "console", "state")[0]
    pipe.estop("estop", source="console")
    assert pipe.wait(lambda: pipe.p.safety_state() == "ESTOP", 5.0)
    pipe.estop("reset", source="console")
    assert pipe.wait(lambda: pipe.p.safety_state() not in ("ESTOP", ""), 5.0)
    time.sleep(0.3)
    with spy.lock:
        spy.recording = False
        names = [q[1] for q in spy.queries]
        n_estop = len(spy.puts["estop"])
    captured = now_ns()
    assert names == ["set_scale", "scale_up", "teach_trocar", "begin_posture_adjust", "state"], names
    assert n_estop == 2 and all(spy.puts[key] for key in PUT_KEYS)
    scale0, trocar0, state0 = a.obs.scale(), trocar[-1], pipe.p.safety_state()

    def check_round(label: str, t0: int, scale: float) -> None:
        time.sleep(0.5)
        moved = attack._motion(pipe, t0, now_ns())
        assert moved is not None and moved < MOTION_LIMIT_MM, f"{label}: the slave moved {moved} mm"
        assert a.obs.scale() == scale, f"{label}: scale {a.obs.scale()} (left at {scale})"
        assert trocar[-1] == trocar0, f"{label}: trocar {trocar[-1]} (taught {trocar0})"
        assert pipe.p.safety_state() == state0, f"{label}: safety state {pipe.p.safety_state()}"

    def replay_round(label: str, scale: float) -> None:
        with pipe.p.lock:
            rej0 = dict(pipe.p.heartbeats)
        t0 = now_ns()
        sent, answers = spy.replay()
        # every replayed query is answered with a refusal by the freshness rules, never handled
        assert len(answers) == 5 and all(x.split(": ", 1)[1].startswith("rejected: ") for x in answers), (
            label,
            answers,
        )
        check_round(label, t0, scale)
        rej = attack._settle_rejections(pipe, ("slave_control", "mapping", "watchdog"), rej0)
        slave_min = sent["slave/arm1/servo_jp"] + sent["safety/arm1/lease"] + sent["estop"] + 3
        mapping_min = sent["master/m1/measured_cp"] + sent["master/m1/buttons"] + 2
        assert rej["slave_control"] >= slave_min, (label, rej, sent)
        assert rej["mapping"] >= mapping_min, (label, rej, sent)
        assert rej["watchdog"] >= sent["estop"] + sent["slave/arm1/servo_jp"], (label, rej, sent)
        print(label, "sent", sent, "rejected", rej, "answers", answers)

    # -- 0.1 s, 1 s, 10 s later ------------------------------------------------------------------
    for delay in (0.1, 1.0, 10.0):
        time.sleep(max(0.0, captured / 1e9 + delay - now_ns() / 1e9))
        replay_round(f"{delay:g} s", scale0)
        if delay == 1.0:
            # another identity's e-stop, then the console's old e-stop and reset again: latched
            pipe.estop("estop", source="bench_operator2")
            assert pipe.wait(lambda: pipe.p.safety_state() == "ESTOP", 5.0)
            spy.replay(only_estop=True)
            time.sleep(1.0)
            assert pipe.p.safety_state() == "ESTOP", "an old reset cleared another identity's e-stop"
            pipe.estop("reset", source="console")  # the operator's fresh reset still clears it
            assert pipe.wait(lambda: pipe.p.safety_state() == state0, 5.0)
    with pipe.p.lock:
        replayed = {src for _, src, kind, text in pipe.p.events if kind == "replayed"}
        texts = [text for _, _, kind, text in pipe.p.events if kind == "replayed"]
    assert {"slave_control", "mapping", "watchdog"} <= replayed, replayed
    for signer in ("mapping", "watchdog", "master_capture", "console"):
        assert any(f"signed by {signer!r}" in t for t in texts), (signer, texts[:20])

    # -- a signed reply of the earlier `state` query, offered for the console's next one -------
    ring = auth.Keyring.load(auth.default_keys_dir(pipe.spec.site))
    old_state = next(q for q in spy.queries if q[1] == "state")
    body = CommandReply(Header("slave_control", 10**6, now_ns()), "arm1", "state", True, "OLD").encode()
    old = auth.Signer("slave_control", ring.keys["slave_control"]).attach(
        auth.REPLY, old_state[0], body, bind=old_state[3]
    )

    def lie(q: Any) -> None:
        with contextlib.suppress(Exception):
            q.reply(sk, body, attachment=old)

    h = spy.session.declare_queryable(sk, lie)
    time.sleep(0.3)
    for _ in range(3):
        ok, reason, _ = a.request(sk, "console", "state")
        assert ok and reason != "OLD", reason
    h.undeclare()

    # -- the mapping restarts: what was captured before its start still gets nowhere ---------------
    pipe.kill("mapping")
    t_restart = now_ns()
    pipe.restart("mapping")
    assert pipe.wait(lambda: any(t > t_restart for t, *_ in a.obs.teleop), 30.0), (
        "the mapping did not come back"
    )
    time.sleep(1.0)
    scale1 = a.obs.scale()
    t0 = now_ns()
    _, answers = spy.replay()
    mapping_answers = [x for x, q in zip(answers, spy.queries, strict=True) if q[0] == mk]
    assert len(mapping_answers) == 2 and all("rejected: stamped" in x for x in mapping_answers), answers
    time.sleep(0.5)
    moved = attack._motion(pipe, t0, now_ns())
    assert moved is not None and moved < MOTION_LIMIT_MM, f"after the restart: the slave moved {moved} mm"
    assert a.obs.scale() == scale1
