"""Issue #17, acceptance 1 (operator authority and the attack bench), with the real services.

``telesurg bench attack --quick``'s cases (tools/bench/attack.py) run against local sites
(router, watchdog, slave_control, mapping, master_capture; the operator's clutch released); each
case's row is judged against the acceptance limits: 0 messages accepted where the rules forbid, slave
motion < 0.5 mm, the genuine faults' time to hold. The operator-authority cases (this branch) and
the forgery cases (message authentication, branch ``auth``, merged) must pass, and so must the
liveliness and local-listener cases (branch ``guard``): a stranger's watchdog tokens do not hide
the watchdog's death (session-keyed tokens; on the locked-down slave site a copy of the genuine
token is refused by the ACL), and a local client without the site's credentials gets no session
on the locked-down slave site.

Then, on a site of its own: the operator console's commands are carried out only with the
confirmation (PTP moves the arm once confirmed), a stranger's PTP / set_scale / reset are
refused with the reason and move nothing.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import Any

import pytest
from telesurg.tools.bench import attack
from telesurg.tools.bench.harness import now_ns

#: the module's fixture runs every case, each forging case on a site of its own (15 sites, about a
#: minute each on the shared 2-core machine under load): longer than the suite's 300 s per test
pytestmark = [pytest.mark.process, pytest.mark.timeout(1800)]

#: the cases this branch's operator authority must pass
AUTHORITY_CASES = (
    "stranger-ptp",
    "stranger-set-scale",
    "stranger-reset",
    "console-ptp",
    "console-scale-follow",
)
#: the cases message authentication (branch auth, merged) must pass
AUTH_CASES = (
    "lease-seq-jump",
    "watchdog-freeze",
    "watchdog-kill",
    "servo-seq-jump",
    "seq0-poison",
    "scale0-state",
)
#: the cases of session-keyed liveliness and the locked-down local listener (branch guard)
GUARD_CASES = ("duplicate-alive", "watchdog-kill-locked", "duplicate-alive-copy", "local-tcp-client")


@pytest.fixture(scope="module")
def rows(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    """The cases of ``telesurg bench attack --quick`` this module judges, by name (the bench's
    ``replay`` case is judged by tests/test_replay_process.py on a site of its own)."""
    judged = AUTHORITY_CASES + AUTH_CASES + GUARD_CASES
    selected = [c for c in attack.cases() if c.name in judged]
    assert {c.name for c in selected} == set(judged)
    out = {r["case"]: r for r in attack.run_cases(tmp_path_factory.mktemp("attack"), selected, quick=True)}
    for r in out.values():
        print(r)
    return out


def _check(row: dict[str, Any]) -> None:
    assert "error" not in row or not row.get("connected", True), row
    if row.get("forbidden"):
        assert row["accepted"] == 0, f"{row['case']}: {row['accepted']} forbidden messages accepted: {row}"
    m = row.get("motion_mm")
    assert m is None or m < attack.MOTION_LIMIT_MM, f"{row['case']}: the slave moved {m} mm: {row}"
    if "time_to_hold_limit_ms" in row:
        # the slave holds; how fast (measured at a probe that carries the host's scheduling delays)
        # is the bench's figure against its limit (`telesurg bench attack` JSON), not a test verdict
        t = row.get("time_to_hold_ms")
        assert t is not None, f"{row['case']}: the slave never held: {row}"
        print(f"{row['case']}: time to hold {t} ms (bench limit {row['time_to_hold_limit_ms']} ms)")


@pytest.mark.parametrize("case", AUTHORITY_CASES + AUTH_CASES)
def test_operator_authority_cases_meet_the_limits(rows: dict[str, dict[str, Any]], case: str) -> None:
    _check(rows[case])
    reply = rows[case].get("reply", "")
    if case.startswith("stranger-") and case != "stranger-reset":
        assert "only the operator console" in reply, reply  # the reason, in the query's error reply
    if case == "console-ptp":
        assert rows[case]["confirm_asked"] and "confirm required" in reply, reply
    if case == "console-scale-follow":
        row = rows[case]
        # judged from the mapping's own answer (the observer's view of the pair may lag on a busy
        # host: 'following' False while the mapping answered "refused while following")
        assert row["answered_following"], (
            f"the mapping answered while not following in every try: the case judged nothing: {row}"
        )


@pytest.mark.parametrize("case", GUARD_CASES)
def test_liveliness_and_local_listener_cases(rows: dict[str, dict[str, Any]], case: str) -> None:
    """0 accepted, < 0.5 mm; the watchdog's death is seen as a death — the slave's hold reason is
    the watchdog's vanished token (``lease: watchdog not alive``), not a lease running out, whoever
    else declares tokens for it (the time to hold is printed with the rows: on the shared 2-core
    machine the probe's receipt carries the host's scheduling delays); a client without the
    site's credentials gets no session on the locked-down slave site and nothing of it arrives."""
    row = rows[case]
    assert "error" not in row or not row.get("connected", True), row
    assert row["accepted"] == 0, f"{case}: {row['accepted']} forbidden messages accepted: {row}"
    m = row.get("motion_mm")
    assert m is not None and m < attack.MOTION_LIMIT_MM, f"{case}: the slave moved {m} mm: {row}"
    if case != "local-tcp-client":
        assert row["time_to_hold_ms"] is not None, f"{case}: the slave never held: {row}"
        assert "watchdog not alive" in (row.get("hold_reason") or ""), row
    if case == "duplicate-alive-copy":
        assert row["site"] == "locked" and row["reached"] == 0, f"the ACL let the forgeries through: {row}"
    if case == "local-tcp-client":
        assert row["site"] == "locked" and not row["connected"], row
        assert row["reached"] == 0, f"messages of a client without credentials reached the site: {row}"


def test_console_commands_run_only_when_confirmed(tmp_path: Path) -> None:
    with contextlib.ExitStack() as stack:
        _console_commands(attack.open_site(stack, tmp_path / "logs", quick=True))


def _console_commands(a: attack.Attacker) -> None:
    pipe = a.pipe
    key = a.k.command("arm1")
    # a stranger: refused with the reason, nothing moves
    t0 = now_ns()
    ok, reason, token = a.request(key, attack.STRANGER, "begin_posture_adjust", "method=ptp")
    assert not ok and not token and "only the operator console" in reason, reason
    # the console without confirming: asked, nothing moves
    ok, reason, token = a.request(key, "console", "begin_posture_adjust", "method=ptp")
    assert not ok and token and "confirm required: begin_posture_adjust method=ptp on arm1" in reason
    time.sleep(2.0)
    still = attack._motion(pipe, t0, now_ns())
    assert still is not None and still < attack.MOTION_LIMIT_MM, f"moved {still} mm without a confirmation"
    # a wrong token is refused; the right one from the console starts the PTP: the arm moves
    ok, reason, _ = a.request(
        key, "console", "begin_posture_adjust", "method=ptp", "confirm=0123456789abcdef"
    )
    assert not ok and "unknown or already used" in reason, reason
    # the right token passes the authority (the PTP from this home would cross the patient: the
    # keep-out refuses it, docs/trocar.md); a confirmed jog up, away from the patient, moves the arm
    ok, reason, _ = a.request(key, "console", "begin_posture_adjust", "method=ptp", f"confirm={token}")
    assert ok or "patient keep-out" in reason, reason
    t1 = now_ns()
    for cmd in (("set_motion_mode", "mode=jog"), ("jog", "frame=base", "axis=z", "direction=1")):
        ok, reason, token = a.request(key, "console", *cmd)
        assert not ok and token and f"confirm required: {cmd[0]}" in reason, reason
        ok, reason, _ = a.request(key, "console", *cmd, f"confirm={token}")
        assert ok, reason
    assert pipe.wait(lambda: (attack._motion(pipe, t1, now_ns()) or 0.0) > 5.0, 15.0), (
        "the confirmed jog did not move"
    )
    a.request(key, "console", "abort")
    # set_scale: a stranger is refused, the console (clutch released) is obeyed at once
    mk = a.k.mapping_command("arm1")
    ok, reason, _ = a.request(mk, attack.STRANGER, "set_scale", "value=0.3")
    assert not ok and "only the operator console" in reason
    ok, reason, token = a.request(mk, "console", "set_scale", "value=0.3")
    assert ok and not token, reason
    assert pipe.wait(lambda: a.obs.scale() == 0.3, 3.0)
    # reset: a stranger's leaves the e-stop latched, the console's clears it
    pipe.estop("estop", source=attack.STRANGER)  # anyone may stop
    assert pipe.wait(lambda: pipe.p.safety_state() == "ESTOP", 5.0)
    pipe.estop("reset", source=attack.STRANGER)
    time.sleep(1.0)
    assert pipe.p.safety_state() == "ESTOP"
    with pipe.p.lock:
        refused = [t for _, _, k, t in pipe.p.events if k == "estop_refused"]
    assert any("only the operator console may reset" in t for t in refused), refused
    pipe.estop("reset", source="console")
    assert pipe.wait(lambda: pipe.p.safety_state() != "ESTOP", 5.0)
