"""A keyring only its owner controls, and identities a remote host cannot borrow (issue #39).

The keyring's folder and every key and link file are refused, with a message saying why, when
another user owns them or can write them, or when they are symbolic links — at load (a process's
start) and when a signer the process did not know yet is looked up. Between two hosts the keys of
a link verify the other host's messages and never make one the slave accepts as an identity the
other host does not run.
"""

from __future__ import annotations

import os
import secrets
import struct
import time
from pathlib import Path

import pytest
from telesurg.services.keys import export
from telesurg.shared import auth
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import CartesianPose, EStop, Header, JointSetpoint, SafetyLease

KEY = "telesurg/t/slave/arm1/servo_jp"
NOBODY = 65534
Hosts = tuple[auth.Keyring, auth.Keyring]
root_only = pytest.mark.skipif(os.geteuid() != 0, reason="giving a file to another user needs root")


def _ring(path: Path, *ids: str) -> Path:
    return auth.init_keyring(path, ids or ("mapping", "watchdog"))


# -- a keyring only its owner controls -------------------------------------------------------------
def test_a_keyring_folder_others_can_write_is_refused(tmp_path: Path) -> None:
    d = _ring(tmp_path / "k")
    os.chmod(d, 0o777)
    with pytest.raises(ConfigError, match=r"keyring .*/k is open to others \(mode 777.*chmod 700"):
        auth.Keyring.load(d)
    os.chmod(d, 0o700)
    assert auth.Keyring.load(d).identities() == ["mapping", "watchdog"]


def test_a_keyring_under_a_folder_others_can_write_is_refused(tmp_path: Path) -> None:
    parent = tmp_path / "shared"
    d = _ring(parent / "k")
    os.chmod(parent, 0o777)  # (not sticky: anyone could rename the keyring away and plant one)
    with pytest.raises(ConfigError, match=r"folder .*/shared above it is writable by others"):
        auth.Keyring.load(d)
    os.chmod(parent, 0o1777)  # sticky, like /tmp: others cannot replace what is ours
    assert auth.Keyring.load(d).identities() == ["mapping", "watchdog"]


def test_symlinked_keyring_and_key_files_are_refused(tmp_path: Path) -> None:
    d = _ring(tmp_path / "k")
    (tmp_path / "link").symlink_to(d)
    with pytest.raises(ConfigError, match="is a symbolic link"):
        auth.Keyring.load(tmp_path / "link")
    elsewhere = _ring(tmp_path / "other", "console")
    (d / "console.key").symlink_to(elsewhere / "console.key")
    with pytest.raises(ConfigError, match=r"key file .*/console.key is a symbolic link"):
        auth.Keyring.load(d)


@root_only
def test_files_another_user_owns_are_refused_at_start(tmp_path: Path) -> None:
    d = _ring(tmp_path / "k")
    os.chown(d / "mapping.key", NOBODY, NOBODY)
    with pytest.raises(
        ConfigError, match=rf"key file .*mapping.key is owned by uid {NOBODY}, not by this user"
    ):
        auth.Keyring.load(d)
    # a keyring folder another user made first (e.g. planted before the owner's first start)
    planted = tmp_path / "planted"
    planted.mkdir(mode=0o700)
    os.chown(planted, NOBODY, NOBODY)
    with pytest.raises(ConfigError, match=rf"keyring .*planted is owned by uid {NOBODY}"):
        auth.Keyring.load(planted)
    with pytest.raises(ConfigError, match=rf"keyring .*planted is owned by uid {NOBODY}"):
        Node(BusConfig(connect=["tcp/127.0.0.1:1"], keys_dir=str(planted)), "t", "watchdog")


@root_only
def test_a_new_signer_is_looked_up_with_the_same_checks(tmp_path: Path) -> None:
    """A key planted after the start (another user's file, a symlink, a loose mode) never makes
    its signer known; a proper one does."""
    ring = auth.Keyring.load(_ring(tmp_path / "k"))
    payload = JointSetpoint(Header("console", 0, time.time_ns()), ("j1",), (0.1,), follow=True).encode()
    attacker = auth.Keyring.load(_ring(tmp_path / "attacker", "console"))
    att = auth.Signer("console", attacker.keys["console"]).attach(auth.PUT, KEY, payload)
    planted = ring.path / "console.key"
    for how in ("other user", "symlink", "mode 644"):
        planted.unlink(missing_ok=True)
        if how == "symlink":
            planted.symlink_to(attacker.path / "console.key")
        else:
            auth.write_key(ring.path, "console", attacker.keys["console"])
            if how == "other user":
                os.chown(planted, NOBODY, NOBODY)
            else:
                os.chmod(planted, 0o644)
        ring._missed.clear()  # (look it up now, not after the 0.25 s pause)
        with pytest.raises(auth.AuthError, match="unknown signer 'console'"):
            auth.verify(ring, auth.PUT, KEY, payload, att)
        assert "console" not in ring.keys, how
    planted.unlink()
    auth.write_key(ring.path, "console", attacker.keys["console"])  # the owner adds it properly
    ring._missed.clear()
    assert auth.verify(ring, auth.PUT, KEY, payload, att).signer == "console"


# -- two hosts: pairwise keys -------------------------------------------------------------------------
@pytest.fixture
def hosts(tmp_path: Path) -> Hosts:
    """A slave site's keyring and a console host's, split as docs/deploy.md describes."""
    site = auth.init_keyring(tmp_path / "site", auth.IDENTITIES)
    export(site, ["master_capture", "console"], "console", "slave-site", tmp_path / "pack")
    return auth.Keyring.load(site), auth.Keyring.load(tmp_path / "pack")


def _signer(ring: auth.Keyring, identity: str) -> auth.Signer:
    return auth.Signer(identity, ring.ensure(identity), links=ring.send_keys())


def _lease(src: str) -> bytes:
    return SafetyLease(Header(src, 0, time.time_ns()), "arm1", True, 250.0, "").encode()


def test_each_host_verifies_the_other(hosts: Hosts) -> None:
    site, console = hosts
    key = "telesurg/t/safety/arm1/lease"
    lease = _lease("watchdog")
    att = _signer(site, "watchdog").attach(auth.PUT, key, lease)
    assert auth.verify(site, auth.PUT, key, lease, att).signer == "watchdog"  # on the site
    assert auth.verify(console, auth.PUT, key, lease, att).signer == "watchdog"  # on the console host
    stop = EStop(Header("console", 0, time.time_ns()), "*", "estop", "test").encode()
    att = _signer(console, "console").attach(auth.PUT, "telesurg/t/estop", stop)
    assert auth.verify(site, auth.PUT, "telesurg/t/estop", stop, att).signer == "console"
    assert auth.verify(console, auth.PUT, "telesurg/t/estop", stop, att).signer == "console"


def test_the_console_hosts_keys_cannot_sign_as_a_site_identity(
    hosts: tuple[auth.Keyring, auth.Keyring],
) -> None:
    """Whatever the console host does with what it holds — its link key, its own identities'
    keys, a key it makes for itself — the site refuses a lease, a setpoint or a reset in the name
    of an identity the console host does not run."""
    site, console = hosts
    messages = {
        "telesurg/t/safety/arm1/lease": lambda src: _lease(src),
        KEY: lambda src: JointSetpoint(Header(src, 0, time.time_ns()), ("j1",), (0.1,), follow=True).encode(),
        "telesurg/t/estop": lambda src: EStop(Header(src, 0, time.time_ns()), "*", "reset", "x").encode(),
    }
    with pytest.raises(ConfigError, match="takes every other identity from host 'slave-site'"):
        console.ensure("watchdog")  # the console host cannot add a site identity for itself
    own_key = secrets.token_bytes(auth.KEY_BYTES)  # a watchdog key it makes anyway
    forgers = {
        "link key": auth.Signer("watchdog", console.links["slave-site"].send),
        "link key + own key": auth.Signer("watchdog", own_key, links=console.send_keys()),
        "the console's own key": auth.Signer("watchdog", console.keys["console"], links=console.send_keys()),
        "the link's receive key": auth.Signer("watchdog", console.links["slave-site"].recv),
    }
    for name, forger in forgers.items():
        for ident in ("watchdog", "mapping", "slave_control"):
            as_ident = auth.Signer(ident, forger.key, links=forger.links)
            for key, make in messages.items():
                payload = make(ident)
                with pytest.raises(auth.AuthError, match="bad authenticator"):
                    auth.verify(site, auth.PUT, key, payload, as_ident.attach(auth.PUT, key, payload))
            assert name


def test_the_site_cannot_sign_as_the_console_hosts_identities(
    hosts: tuple[auth.Keyring, auth.Keyring],
) -> None:
    site, console = hosts
    with pytest.raises(ConfigError, match="identity 'console' runs on host 'console'"):
        site.ensure("console")
    stop = EStop(Header("console", 0, time.time_ns()), "*", "reset", "x").encode()
    forged = auth.Signer("console", site.links["console"].send).attach(auth.PUT, "telesurg/t/estop", stop)
    with pytest.raises(auth.AuthError, match="bad authenticator"):
        auth.verify(console, auth.PUT, "telesurg/t/estop", stop, forged)


def test_a_link_file_is_checked_like_a_key(tmp_path: Path, hosts: Hosts) -> None:
    site, _ = hosts
    link = site.path / "console.link"
    os.chmod(link, 0o644)
    with pytest.raises(ConfigError, match=r"link file .*console.link is open to others"):
        auth.Keyring.load(site.path)
    os.chmod(link, 0o600)
    text = link.read_text()
    link.write_text(text.replace('"host": "console"', '"host": "elsewhere"'))
    with pytest.raises(ConfigError, match="names host 'elsewhere', not its file name"):
        auth.Keyring.load(site.path)
    link.write_text("{}")
    with pytest.raises(ConfigError, match="not a telesurg link"):
        auth.Keyring.load(site.path)


def test_a_sealed_sample_opens_on_both_hosts_and_nowhere_else(hosts: Hosts, tmp_path: Path) -> None:
    """The datagram link's samples: encrypted on the wire (no field of the pose readable), opened
    by the site and by the console host's own services, by no other keyring; a changed byte or
    another key expression does not open."""
    site, console = hosts
    key = "telesurg/t/master/m1/measured_cp"
    pose = CartesianPose(Header("master_capture", 7, time.time_ns()), "master", (0.125, -0.25, 0.5))
    plain = pose.encode()
    sealed = auth.Sealer(console, "master_capture").seal(key, plain)
    assert auth.is_sealed(sealed) and not auth.is_sealed(plain)
    assert b"master" not in sealed and struct.pack(">d", 0.125) not in sealed  # nothing readable
    assert auth.Sealer(console, "master_capture").seal(key, plain) != sealed  # a fresh nonce each time
    att = _signer(console, "master_capture").attach(auth.PUT, key, sealed)
    for ring in (site, console):  # signed over the sealed bytes, then opened
        who = auth.verify(ring, auth.PUT, key, sealed, att)
        assert auth.unseal(ring, who.signer, key, sealed) == plain
    stranger = auth.Keyring.load(auth.init_keyring(tmp_path / "stranger", auth.IDENTITIES))
    with pytest.raises(auth.AuthError, match="does not open"):
        auth.unseal(stranger, "master_capture", key, sealed)
    flipped = sealed[:-1] + bytes((sealed[-1] ^ 1,))
    for bad_key, data in ((key, flipped), ("telesurg/t/master/m1/buttons", sealed), (key, sealed[:20])):
        with pytest.raises(auth.AuthError):
            auth.unseal(site, "master_capture", bad_key, data)
