"""Operator authority (shared/authority.py): the table, the two-step confirmation, the e-stop and
reset rules, the mapping's bound on a scale change while following — unit level, plus the
refusal as a query's error reply through a real zenoh session."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from telesurg.services.mapping import MappingConfig, guarded
from telesurg.services.slave_control import SlaveControlConfig
from telesurg.services.watchdog import WatchdogConfig
from telesurg.shared.authority import CONFIRM_ARG, MAX_PENDING, Authority, AuthorityConfig
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.config import load_config
from telesurg.shared.errors import AuthorityError, ConfigError, MessageError
from telesurg.shared.messages import Command, CommandReply, Header
from telesurg.shared.teleop.scale import follow_step_problem


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def cmd(src: str, name: str, *args: str, arm: str = "arm1") -> Command:
    return Command(Header(src, 1, time.time_ns()), arm, name, args)


def test_strangers_are_refused_everything_but_read_only_and_stopping() -> None:
    auth = Authority(AuthorityConfig())
    assert auth.check(cmd("intruder", "state")).command is not None
    assert auth.check(cmd("intruder", "programs")).command is not None
    assert auth.check(cmd("intruder", "stop")).kind == "stop"  # fail-safe, like an e-stop
    for name, args in [
        ("begin_posture_adjust", ("method=ptp",)),
        ("set_scale", ("value=2.0",)),
        ("insert", ()),
        ("teach_trocar", ()),
        ("unknown_new_command", ()),
    ]:
        with pytest.raises(AuthorityError, match="only the operator console"):
            auth.check(cmd("mapping", name, *args))
    assert auth.refused == 5
    # a forged confirmation token from a stranger is refused as a stranger
    with pytest.raises(AuthorityError):
        auth.check(cmd("intruder", "insert", f"{CONFIRM_ARG}=00"))


def test_operator_commands_without_motion_pass_at_once() -> None:
    auth = Authority(AuthorityConfig())
    v = auth.check(cmd("console", "set_scale", "value=0.3"))
    assert v.command is not None and v.command.args == ("value=0.3",) and v.kind == "operator"
    assert auth.check(cmd("console", "teach_trocar")).command is not None


def test_motion_needs_a_confirmation_from_the_same_console_within_the_window() -> None:
    clock = Clock()
    auth = Authority(AuthorityConfig(confirm_s=5.0), clock)
    first = auth.check(cmd("console", "begin_posture_adjust", "method=ptp"))
    assert first.command is None and first.token and "confirm required" in first.reason
    assert "begin_posture_adjust method=ptp on arm1" in first.reason
    clock.t += 4.0
    ok = auth.check(cmd("console", "begin_posture_adjust", "method=ptp", f"confirm={first.token}"))
    assert ok.command is not None and ok.kind == "confirmed"
    assert ok.command.args == ("method=ptp",)  # the handler never sees the token
    # single use
    with pytest.raises(AuthorityError, match="unknown or already used"):
        auth.check(cmd("console", "begin_posture_adjust", "method=ptp", f"confirm={first.token}"))
    # too late
    t = auth.check(cmd("console", "insert")).token
    clock.t += 5.5
    with pytest.raises(AuthorityError, match="late"):
        auth.check(cmd("console", "insert", f"confirm={t}"))
    # the token confirms only the command it was issued for, from the console it was issued to
    t = auth.check(cmd("console", "jog", "axis=x", "direction=1")).token
    with pytest.raises(AuthorityError, match="the token confirms jog"):
        auth.check(cmd("console", "jog", "axis=x", "direction=-1", f"confirm={t}"))
    t = auth.check(cmd("console", "remove")).token
    with pytest.raises(AuthorityError):
        auth.check(cmd("console", "remove", f"confirm={t}", arm="arm2"))
    assert auth.pending == 0


def test_pending_tokens_are_bounded() -> None:
    auth = Authority(AuthorityConfig())
    tokens = [auth.check(cmd("console", "insert")).token for _ in range(MAX_PENDING + 10)]
    assert auth.pending == MAX_PENDING
    with pytest.raises(AuthorityError):  # the oldest were dropped
        auth.check(cmd("console", "insert", f"confirm={tokens[0]}"))
    assert auth.check(cmd("console", "insert", f"confirm={tokens[-1]}")).command is not None


def test_confirmation_can_be_switched_off() -> None:
    auth = Authority(AuthorityConfig(confirm_s=0.0))
    assert auth.check(cmd("console", "insert")).command is not None
    with pytest.raises(AuthorityError):
        auth.check(cmd("intruder", "insert"))


def test_estop_from_anyone_reset_only_from_the_console() -> None:
    auth = Authority(AuthorityConfig())
    assert auth.estop_problem("intruder", "estop") == ""
    assert "only the operator console may reset" in auth.estop_problem("intruder", "reset")
    assert auth.estop_problem("console", "reset") == ""
    strict = Authority(AuthorityConfig(estop_sources=["console", "watchdog"]))
    assert "not an e-stop source" in strict.estop_problem("intruder", "estop")
    assert strict.estop_problem("watchdog", "estop") == ""


def test_bad_tables_are_refused() -> None:
    with pytest.raises(ConfigError, match="nobody could stop"):
        AuthorityConfig(estop_sources=[])
    with pytest.raises(ConfigError, match="confirm_s"):
        AuthorityConfig(confirm_s=-1.0)
    with pytest.raises(ConfigError, match="not a service id"):
        AuthorityConfig(operators=["con sole"])


def test_site_authority_table_reaches_every_service(tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text('[site]\nrobot = "mh3f"\n[site.authority]\noperators = ["surgeon"]\nconfirm_s = 3.0\n')
    for cls, table in [
        (SlaveControlConfig, "slave_control"),
        (MappingConfig, "mapping"),
        (WatchdogConfig, "watchdog"),
    ]:
        cfg = load_config(cls, str(site), [], table)
        assert cfg.authority.operators == ["surgeon"] and cfg.authority.confirm_s == 3.0, cls


def test_scale_rises_one_step_at_most_while_following() -> None:
    assert follow_step_problem(0.5, 0.7) == ""
    assert follow_step_problem(0.5, 0.3) == ""  # lowering is always fine
    assert "at most one step up (to 0.7)" in follow_step_problem(0.5, 2.0)
    assert follow_step_problem(1.5, 2.0) == ""


def test_refusal_is_the_query_error_reply_and_confirm_round_trip(endpoint: str) -> None:
    bus = BusConfig(connect=[endpoint])
    done: list[Command] = []

    def handler(c: Command) -> CommandReply:
        done.append(c)
        return CommandReply(Header("mapping", len(done), time.time_ns()), c.arm, c.name, True, "ok")

    with (
        Node(bus, "t", "mapping") as server,
        Node(bus, "t", "intruder") as client,  # (each identity signs as itself)
        Node(bus, "t", "console") as console,
    ):
        server.serve(
            server.keys.mapping_command("arm1"),
            Command,
            guarded(server, Authority(AuthorityConfig()), "arm1", handler),
        )
        key = client.keys.mapping_command("arm1")
        time.sleep(0.3)
        with pytest.raises(MessageError, match="refused: set_vip from 'intruder' refused: only the operator"):
            client.request(key, cmd("intruder", "set_vip", "x=1", "y=2", "z=3"), CommandReply, 3.0)
        r = console.request(key, cmd("console", "set_vip", "x=1", "y=2", "z=3"), CommandReply, 3.0)
        assert not r.accepted and r.confirm and "confirm required" in r.reason
        assert not done
        r2 = console.request(
            key, cmd("console", "set_vip", "x=1", "y=2", "z=3", f"confirm={r.confirm}"), CommandReply, 3.0
        )
        assert r2.accepted and [c.args for c in done] == [("x=1", "y=2", "z=3")]
        assert server.streams.get(key).rejected == 1


def test_telesurg_cmd_confirms_only_with_yes(endpoint: str, capsys: pytest.CaptureFixture[str]) -> None:
    from telesurg.services.command import main as cmd_main

    bus = BusConfig(connect=[endpoint])
    done: list[Command] = []

    def handler(c: Command) -> CommandReply:
        done.append(c)
        return CommandReply(Header("mapping", len(done), time.time_ns()), c.arm, c.name, True, "VIP set")

    with Node(bus, "t", "mapping") as server:
        server.serve(
            server.keys.mapping_command("arm1"),
            Command,
            guarded(server, Authority(AuthorityConfig()), "arm1", handler),
        )
        time.sleep(0.3)
        base = ["--site", "t", "--connect", endpoint, "--mapping", "set_vip", "x=1", "y=2", "z=3"]
        # no terminal, no --yes: asked, not carried out
        assert cmd_main(base) == 1
        assert "not confirmed: confirm required: set_vip x=1 y=2 z=3 on arm1" in capsys.readouterr().out
        assert not done
        assert cmd_main([*base, "--yes"]) == 0
        assert "accepted: VIP set" in capsys.readouterr().out
        assert [c.args for c in done] == [("x=1", "y=2", "z=3")]
        # a stranger: refused with the reason
        assert cmd_main([*base, "--yes", "--as", "intruder"]) == 1
        assert (
            "refused: set_vip from 'intruder' refused: only the operator console" in capsys.readouterr().out
        )
        assert len(done) == 1
