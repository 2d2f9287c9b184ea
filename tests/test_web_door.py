"""The door of a local page (login token → session, Host, Origin) and the one controlling page,
as pure logic (shared/door.py, control.py)."""

from __future__ import annotations

import pytest
from telesurg.services.console.control import Control
from telesurg.services.console.webconfig import WebConfig
from telesurg.shared.door import Door
from telesurg.shared.errors import ConfigError


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def door(clock: Clock | None = None) -> Door:
    return Door("127.0.0.1", 8470, session_s=3600.0, clock=clock or Clock())


OWN = {"Host": "127.0.0.1:8470"}


def logged_in(d: Door) -> dict[str, str]:
    got = d.login(d.mint())
    assert got is not None
    return {d.cookie_name: got[0]}


def test_a_login_token_works_once_and_gives_an_expiring_session() -> None:
    clock = Clock()
    d = door(clock)
    token = d.mint()
    got = d.login(token)
    assert got is not None
    value, s = got
    assert d.session(value) is s
    assert d.login(token) is None, "a login token worked twice"
    assert d.counts() == {"login": 1}
    clock.t += 3601.0
    assert d.session(value) is None, "a session outlived session_s"
    assert d.admit("GET", "/", OWN, {d.cookie_name: value}, False).status == 401


def test_a_page_makes_a_login_link_that_expires() -> None:
    clock = Clock()
    d = door(clock)
    token = d.mint(ttl_s=60.0)
    clock.t += 61.0
    assert d.login(token) is None


def test_the_cookie_is_http_only_and_same_site_strict() -> None:
    d = door()
    header = d.cookie_header("v")
    assert header.startswith("telesurg_session_8470=v;")
    assert "HttpOnly" in header and "SameSite=Strict" in header and "Path=/" in header


@pytest.mark.parametrize(
    ("headers", "ws", "method", "status", "kind"),
    [
        ({"Host": "rebind.example:8470"}, False, "GET", 403, "host"),
        ({"Host": "127.0.0.1:9999"}, False, "GET", 403, "host"),
        ({"Host": "127.0.0.1:8470", "Origin": "http://127.0.0.1:28999"}, False, "GET", 403, "origin"),
        ({"Host": "127.0.0.1:8470", "Origin": "null"}, True, "GET", 403, "origin"),
        ({"Host": "127.0.0.1:8470"}, True, "GET", 403, "origin"),  # a websocket without Origin
        ({"Host": "127.0.0.1:8470"}, False, "POST", 403, "origin"),  # a change without Origin
    ],
)
def test_foreign_host_and_origin_are_refused_even_with_the_session(
    headers: dict[str, str], ws: bool, method: str, status: int, kind: str
) -> None:
    d = door()
    cookies = logged_in(d)
    v = d.admit(method, "/ws" if ws else "/api/state", headers, cookies, ws)
    assert (v.status, v.kind) == (status, kind) and v.reason.startswith("refused: ")
    assert d.counts() == {kind: 1}


@pytest.mark.parametrize("host", ["127.0.0.1:8470", "localhost:8470", "LOCALHOST:8470", "[::1]:8470"])
def test_the_page_is_served_by_its_own_names_with_the_session(host: str) -> None:
    d = door()
    cookies = logged_in(d)
    assert d.admit("GET", "/", {"Host": host}, cookies, False).ok
    v = d.admit("GET", "/ws", {"Host": host, "Origin": f"http://{host}"}, cookies, True)
    assert v.ok and v.session
    assert d.admit("GET", "/", {"Host": host}, {}, False).status == 401


def test_allowed_hosts_add_a_lan_name() -> None:
    d = Door("0.0.0.0", 8470, allowed_hosts=("192.168.1.20",))
    cookies = logged_in(d)
    assert d.admit("GET", "/", {"Host": "192.168.1.20:8470"}, cookies, False).ok
    assert d.admit("GET", "/", {"Host": "192.168.1.21:8470"}, cookies, False).kind == "host"


def test_the_login_path_needs_no_session_but_a_good_host() -> None:
    d = door()
    assert d.admit("GET", "/login", OWN, {}, False).ok
    assert d.admit("GET", "/login", {"Host": "rebind.example:8470"}, {}, False).kind == "host"


@pytest.mark.parametrize(
    ("field", "value"),
    [("session_s", 10.0), ("invite_s", 0.0), ("control_grace_s", 0.0), ("allowed_hosts", ["a:80"])],
)
def test_bad_door_settings_are_refused(field: str, value: object) -> None:
    cfg = WebConfig(**{field: value})  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=field):
        cfg.validate()


def test_one_controller_control_moves_only_by_an_explicit_handover() -> None:
    clock = Clock()
    c = Control(grace_s=10.0, clock=clock)
    assert c.join("a") and c.is_controller("a")
    assert c.join("b") == "" and not c.is_controller("b")
    # the viewer asks: the controller keeps control until it answers
    granted, text = c.take("b")
    assert not granted and "asks" in text and c.is_controller("a")
    assert c.answer("b", True) == "", "a viewer answered its own request"
    assert c.answer("a", False).startswith("page a refused") and c.is_controller("a")
    c.take("b")
    assert c.answer("a", True) == "page a handed control to page b"
    assert c.is_controller("b") and not c.is_controller("a")
    # a release: nobody in control until a page takes it
    assert c.release("a") == "" and c.release("b") == "page b released control"
    assert c.snapshot() == (None, None)
    assert c.take("a")[0] and c.is_controller("a")


def test_a_short_pause_of_the_controller_does_not_hand_control_on() -> None:
    clock = Clock()
    c = Control(grace_s=10.0, clock=clock)
    c.join("a")
    c.join("b")
    c.leave("a")  # the operator's page blinks (a reload, a network blip)
    clock.t += 0.15
    assert c.take("b")[0] is False and c.is_controller("a")
    c.join("a")
    clock.t += 60.0
    assert c.take("b")[0] is False, "a connected controller lost control without answering"
    c.leave("a")
    clock.t += 10.0
    granted, text = c.take("b")  # gone for grace_s: an explicit take succeeds
    assert granted and "its page was gone" in text


def test_a_controller_whose_session_ended_can_be_replaced() -> None:
    alive = {"a": True}
    c = Control(alive=lambda page: alive.get(page, False))
    c.join("a")
    c.join("b")
    alive["a"] = False
    granted, text = c.take("b")
    assert granted and "session ended" in text
