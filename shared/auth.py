"""Per-service message authentication: a site keyring, HMAC-SHA256 authenticators in the zenoh
attachment, per-process session ids.

**Keyring.** A directory (mode 0700, owned by the user that runs the services, not a symlink) with
one file per identity this host runs, ``<identity>.key`` (mode 0600, owned by that user, a regular
file, the 32-byte key in hex, from :mod:`secrets`), and one ``<host>.link`` file (same rules) per
other host of the site: the pairwise keys of the link and the identities that host may sign as
(:class:`Link`; ``telesurg keys export --to HOST`` makes both ends). An identity is a service
instance id (the header ``src`` it publishes under: ``watchdog``, ``mapping``, ``console``, …).
``telesurg keys init DIR`` makes one; ``telesurg up`` / ``demo`` make the default one if it is
absent; every process loads it (:func:`default_keys_dir`; ``--keyring DIR`` on every command line,
``--keys DIR`` for ``up`` / ``demo``; ``BusConfig.keys_dir``). Nothing secret is in the repository.
A process whose own identity has no key yet adds one to a keyring it can write
(:meth:`Keyring.ensure`): anyone who can write the keyring can read every key in it anyway.
Receivers look a signer they do not know up in the directory again, at most every 0.25 s per name (a
key added after they started).

**Authenticator.** Every publication, query and reply made through :class:`~telesurg.shared.bus.Node`
carries, in the zenoh *attachment* (the msgpack payload is unchanged)::

    b"T1" | sid (8 bytes) | len(signer) (1 byte) | signer (ASCII) | mac (16 bytes) × n

one ``mac`` per audience: the first under the signer's own key (receivers on its host), then one
under the send key of each link to another host. A receiver checks the one MAC it can make: the
signer's key if the signer runs on this host, the link's receive key if a link names the signer.
So a host can verify what another host's identities send, and cannot make what any of them sends
to a third host, nor sign as an identity its links do not name.

``mac`` = HMAC-SHA256(key[signer], kind | sid | len(signer) | signer | len(key_expr) (2 bytes,
big-endian) | key_expr | payload), truncated to 16 bytes; ``kind`` is ``P`` (put), ``Q`` (query)
or ``R`` (reply). So a message cannot be moved to another key expression, turned from a
publication into a command, or claimed by another signer. ``sid`` is a random 64-bit session id
per process (per :class:`Signer`): a restarted publisher is recognised by a new authenticated
``sid`` (``shared/streams.py``), never by its sequence number going back to 0. The receiver also
requires the signer to equal the decoded header ``src`` (checked in the bus).

**Sealed payloads** (the datagram link, which has no TLS): the payload itself is encrypted,
``0xC1`` (a byte MessagePack never uses) | nonce (12 bytes, random) | ChaCha20-Poly1305 of the
msgpack payload with the key expression as associated data, under a key derived (HKDF-SHA256) from
the key of the host pair the sample crosses: the link's ``send`` key at the sender (its own key on
a host without links), which the other host holds as its ``recv``. The authenticator is made over
the sealed bytes, so a receiver checks it first and opens the payload after (:class:`Sealer`,
:func:`unseal`).

Ed25519 (``cryptography``) was measured beside HMAC for the 1 kHz path: see docs/security.md.
"""

from __future__ import annotations

import errno
import hmac
import json
import logging
import os
import re
import secrets
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from telesurg.shared.errors import ConfigError, MessageError

log = logging.getLogger(__name__)

MAGIC = b"T1"
SID_BYTES = 8
MAC_BYTES = 16
KEY_BYTES = 32
KEY_SUFFIX = ".key"
LINK_SUFFIX = ".link"
#: most MACs an attachment carries (its own host + one per link)
MAX_MACS = 16
PUT, QUERY, REPLY = b"P", b"Q", b"R"
#: s between two directory look-ups of the same unknown signer
LOOKUP_INTERVAL_S = 0.25
_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
#: environment variable naming the keyring directory (read once, by :func:`default_keys_dir`)
KEYS_ENV = "TELESURG_KEYS"


class AuthError(MessageError):
    """A message failed authentication (no or malformed attachment, unknown signer, bad MAC,
    signer not the header source)."""


def default_keys_dir(site: str) -> Path:
    """The keyring a process uses when none is given: ``$TELESURG_KEYS`` if set, else
    ``$XDG_STATE_HOME/telesurg/<site>/keys`` (``~/.local/state/telesurg/<site>/keys``)."""
    env = os.environ.get(KEYS_ENV)
    if env:
        return Path(env)
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state) / "telesurg" / site / "keys"


def check_id_name(what: str, name: str) -> str:
    """``name`` if it is a valid identity or host name, else ConfigError."""
    if not _ID.match(name):
        raise ConfigError(f"{what} {name!r} must match [A-Za-z0-9_-]{{1,64}}")
    return name


def _check_identity(identity: str) -> str:
    return check_id_name("key identity", identity)


def _owned_private(path: Path, what: str, st: os.stat_result) -> None:
    """ConfigError unless ``st`` (an lstat of ``path``) is owned by this user and not open to others."""
    if stat.S_ISLNK(st.st_mode):
        raise ConfigError(f"{what} {path} is a symbolic link; keep the real file in the keyring")
    if st.st_uid != os.geteuid():
        raise ConfigError(
            f"{what} {path} is owned by uid {st.st_uid}, not by this user (uid {os.geteuid()}): "
            "someone else made it; remove it and make the keyring again"
        )
    mode = stat.S_IMODE(st.st_mode)
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        want = "700" if stat.S_ISDIR(st.st_mode) else "600"
        raise ConfigError(
            f"{what} {path} is open to others (mode {mode:o}: readable or writable by group or "
            f"others); chmod {want} it"
        )


def check_keyring_dir(directory: Path) -> None:
    """ConfigError unless ``directory`` is a real directory (no symlink) owned by this user with
    mode 0700, in folders that no other user can write (owned by this user or root, not writable
    by group or others, unless sticky like /tmp): nobody else can add, swap or read a key."""
    try:
        st = os.lstat(directory)
    except FileNotFoundError:
        raise ConfigError(
            f"no keyring at {directory}: make one with `telesurg keys init {directory}` "
            "(telesurg up / demo make the default one), or pass --keyring DIR"
        ) from None
    if not stat.S_ISLNK(st.st_mode) and not stat.S_ISDIR(st.st_mode):
        raise ConfigError(f"keyring {directory} is not a directory")
    _owned_private(directory, "keyring", st)
    parent = Path(os.path.abspath(directory)).parent
    while True:
        pst = os.stat(parent)
        if pst.st_uid not in (0, os.geteuid()):
            raise ConfigError(
                f"keyring {directory}: the folder {parent} above it is owned by uid {pst.st_uid}, "
                "who could replace the keyring; keep it under folders of this user or root"
            )
        if pst.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and not pst.st_mode & stat.S_ISVTX:
            raise ConfigError(
                f"keyring {directory}: the folder {parent} above it is writable by others (mode "
                f"{stat.S_IMODE(pst.st_mode):o}), who could replace the keyring"
            )
        if parent.parent == parent:
            return
        parent = parent.parent


def _read_private(path: Path, what: str) -> str:
    """Text of a key or link file that passes :func:`_owned_private` (opened without following a
    symlink, checked on the opened file: it cannot be swapped in between)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ConfigError(
                f"{what} {path} is a symbolic link; keep the real file in the keyring"
            ) from None
        raise
    with os.fdopen(fd) as f:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{what} {path} is not a regular file")
        _owned_private(path, what, st)
        return f.read()


def _read_key(path: Path) -> bytes:
    text = _read_private(path, "key file")
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise ConfigError(f"key file {path}: not a hex key") from None
    if len(key) != KEY_BYTES:
        raise ConfigError(f"key file {path}: {len(key)} bytes, expected {KEY_BYTES}")
    return key


@dataclass(frozen=True)
class Link:
    """The keys between this host and another host of the site (``<host>.link``, JSON).

    ``send`` signs what this host's identities send (the other host verifies with it), ``recv``
    verifies what the other host sends; ``claims`` are the identities the other host may sign as
    (``("*",)``: every identity that is not this host's own — the site, as seen from a console
    host). Pairwise keys: the other host can make ``recv``-MACs, which only this host accepts, and
    only for the identities in ``claims``."""

    host: str
    claims: tuple[str, ...]
    send: bytes
    recv: bytes

    def to_json(self) -> str:
        return json.dumps(
            {
                "host": self.host,
                "claims": list(self.claims),
                "send": self.send.hex(),
                "recv": self.recv.hex(),
            },
            indent=1,
        )

    @classmethod
    def read(cls, path: Path) -> Link:
        """Parse a link file; ConfigError naming what is wrong."""
        try:
            d = json.loads(_read_private(path, "link file"))
            link = cls(
                str(d["host"]),
                tuple(str(c) for c in d["claims"]),
                bytes.fromhex(d["send"]),
                bytes.fromhex(d["recv"]),
            )
        except (ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"link file {path}: not a telesurg link ({exc})") from None
        if link.host != path.name[: -len(LINK_SUFFIX)]:
            raise ConfigError(f"link file {path}: names host {link.host!r}, not its file name")
        for c in link.claims:
            if c != "*":
                _check_identity(c)
        if len(link.send) != KEY_BYTES or len(link.recv) != KEY_BYTES:
            raise ConfigError(f"link file {path}: keys must be {KEY_BYTES} bytes")
        return link


def write_private(directory: Path, name: str, text: str) -> bool:
    """Write ``text`` into ``directory/name`` (mode 0600) unless it exists; False if it did."""
    path = directory / name
    if os.path.lexists(path):
        return False
    # written whole under a temporary name, then linked into place (fails if the name exists):
    # a reader never sees a half-written key, and two processes adding one identity agree
    tmp = directory / f".{name}.{secrets.token_hex(8)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.link(tmp, path)
    except FileExistsError:
        return False
    finally:
        tmp.unlink(missing_ok=True)
    return True


def write_key(directory: Path, identity: str, key: bytes | None = None) -> bool:
    """Write ``identity``'s key (new random one unless given) into ``directory``, mode 0600.

    Returns False (and leaves the file alone) when the identity already has a key."""
    _check_identity(identity)
    key = key if key is not None else secrets.token_bytes(KEY_BYTES)
    if len(key) != KEY_BYTES:
        raise ConfigError(f"key of {identity}: {len(key)} bytes, expected {KEY_BYTES}")
    return write_private(directory, f"{identity}{KEY_SUFFIX}", key.hex() + "\n")


def init_keyring(directory: str | Path, identities: list[str] | tuple[str, ...] = ()) -> Path:
    """Create ``directory`` (mode 0700) with a key for each identity that has none; returns it."""
    d = Path(directory)
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    for identity in identities:
        write_key(d, identity)
    return d


#: Identities a site keyring starts with: the site's services and operator tools (any other
#: identity adds its own key on first use to a keyring it can write).
IDENTITIES = ("master_capture", "mapping", "slave_control", "watchdog", "mirror", "console", "record")


def ensure_keyring(directory: str | Path) -> tuple[Path, bool]:
    """The keyring at ``directory``, made (with :data:`IDENTITIES`) if absent: (path, made)."""
    d = Path(directory)
    made = not d.is_dir()
    if made:
        init_keyring(d, IDENTITIES)
    return d, made


@dataclass
class Keyring:
    """The keys of this host: its identities' keys and its links to the site's other hosts."""

    path: Path
    keys: dict[str, bytes] = field(default_factory=dict)
    links: dict[str, Link] = field(default_factory=dict)
    _missed: dict[str, float] = field(default_factory=dict)  # unknown signer -> last look-up (monotonic s)

    @classmethod
    def load(cls, directory: str | Path) -> Keyring:
        """Load every ``*.key`` and ``*.link`` of ``directory``; ConfigError (saying what to do) if
        it is absent or any of it is not this user's alone (:func:`check_keyring_dir`)."""
        d = Path(directory)
        check_keyring_dir(d)
        ring = cls(d)
        for p in sorted(d.glob(f"*{KEY_SUFFIX}")):
            ring.keys[p.name[: -len(KEY_SUFFIX)]] = _read_key(p)
        for p in sorted(d.glob(f"*{LINK_SUFFIX}")):
            link = Link.read(p)
            ring.links[link.host] = link
        return ring

    def identities(self) -> list[str]:
        """This host's identities, sorted."""
        return sorted(self.keys)

    def send_keys(self) -> tuple[bytes, ...]:
        """The keys this host's messages are also signed with: one per link."""
        return tuple(link.send for _, link in sorted(self.links.items()))

    def verifier(self, identity: str) -> bytes | None:
        """The key that checks a message signed as ``identity`` on this host: the receive key of
        the link that names it, else its own key (looked up on disk at most every
        :data:`LOOKUP_INTERVAL_S` while unknown), else the receive key of a link that claims every
        identity this host does not run; None if nothing here can check it."""
        for link in self.links.values():
            if identity in link.claims:
                return link.recv
        k = self.key(identity)
        if k is not None:
            return k
        for link in self.links.values():
            if "*" in link.claims:
                return link.recv
        return None

    def key(self, identity: str) -> bytes | None:
        """``identity``'s own key; an unknown one is looked up on disk at most every
        :data:`LOOKUP_INTERVAL_S` (the keyring's folder and the file checked again each time)."""
        k = self.keys.get(identity)
        if k is not None:
            return k
        if not _ID.match(identity):
            return None
        now = time.monotonic()
        if now - self._missed.get(identity, -LOOKUP_INTERVAL_S) < LOOKUP_INTERVAL_S:
            return None
        self._missed[identity] = now
        if len(self._missed) > 4096:  # a stranger cycling names: forget the oldest look-ups
            self._missed.clear()
        p = self.path / f"{identity}{KEY_SUFFIX}"
        if not os.path.lexists(p):
            return None
        try:
            check_keyring_dir(self.path)
            k = _read_key(p)
        except (OSError, ConfigError) as exc:
            log.error("key of %r not taken: %s", identity, exc)
            return None
        self.keys[identity] = k
        self._missed.pop(identity, None)
        return k

    def ensure(self, identity: str) -> bytes:
        """``identity``'s key, added to the keyring directory if it has none (and it is writable)."""
        k = self.key(identity) or self.keys.get(identity)
        if k is not None:
            return k
        for link in self.links.values():
            if "*" in link.claims:
                raise ConfigError(
                    f"identity {identity!r} has no key on this host, whose keyring {self.path} takes "
                    f"every other identity from host {link.host!r}: export it from there "
                    f"(`telesurg keys export {identity} --to HOST`)"
                )
            if identity in link.claims:
                raise ConfigError(
                    f"identity {identity!r} runs on host {link.host!r} "
                    f"({self.path / (link.host + LINK_SUFFIX)}): its key is there, not here"
                )
        p = self.path / f"{identity}{KEY_SUFFIX}"
        try:
            check_keyring_dir(self.path)
            if write_key(self.path, identity):
                log.info("added a key for %s to the keyring %s", identity, self.path)
            k = _read_key(p)
        except OSError as exc:
            raise ConfigError(
                f"keyring {self.path} has no key for {identity!r} and it cannot be added ({exc}); "
                f"add one with `telesurg keys add {self.path} {identity}`"
            ) from None
        self.keys[identity] = k
        return k


SEALED = 0xC1  # first byte of a sealed payload (never the first byte of a msgpack one)
NONCE_BYTES = 12
_SEAL_INFO = b"telesurg sealed payload v1"
_aeads: dict[bytes, Any] = {}


def _aead(key: bytes) -> Any:
    """The ChaCha20-Poly1305 of the sealing key derived from ``key`` (cached)."""
    a = _aeads.get(key)
    if a is None:
        from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
        from cryptography.hazmat.primitives.hashes import SHA256
        from cryptography.hazmat.primitives.kdf.hkdf import HKDF

        derived = HKDF(algorithm=SHA256(), length=32, salt=None, info=_SEAL_INFO).derive(key)
        a = _aeads[key] = ChaCha20Poly1305(derived)
    return a


class Sealer:
    """Encrypts one sender's payloads for the host pair they cross (see the module's notes)."""

    def __init__(self, ring: Keyring, identity: str) -> None:
        if len(ring.links) > 1:
            raise ConfigError(
                f"sealed (datagram) streams cross one link; this host's keyring {ring.path} has "
                f"{len(ring.links)}: {', '.join(sorted(ring.links))}"
            )
        link = next(iter(ring.links.values()), None)
        self._aead = _aead(link.send if link is not None else ring.ensure(identity))

    def seal(self, key_expr: str, payload: bytes) -> bytes:
        """``payload`` published on ``key_expr``, encrypted."""
        nonce = secrets.token_bytes(NONCE_BYTES)
        body: bytes = self._aead.encrypt(nonce, payload, key_expr.encode())
        return bytes((SEALED,)) + nonce + body


def is_sealed(payload: bytes) -> bool:
    """Whether ``payload`` is sealed (:class:`Sealer`)."""
    return payload[:1] == bytes((SEALED,))


def unseal(ring: Keyring, signer: str, key_expr: str, payload: bytes) -> bytes:
    """The msgpack payload inside a sealed one from ``signer`` (verified already); AuthError if no
    key of this host opens it."""
    from cryptography.exceptions import InvalidTag

    if len(payload) < 1 + NONCE_BYTES + 16:
        raise AuthError("sealed payload too short")
    nonce, body = payload[1 : 1 + NONCE_BYTES], payload[1 + NONCE_BYTES :]
    # a signer of another host: its link's receive key; one of this host: the key it sealed with
    # (its link's send key, or its own on a host without links)
    keys = [link.recv for link in ring.links.values() if signer in link.claims or "*" in link.claims]
    own = ring.key(signer)
    if own is not None:
        keys += [*(link.send for link in ring.links.values()), own]
    for k in keys:
        try:
            out: bytes = _aead(k).decrypt(nonce, body, key_expr.encode())
            return out
        except InvalidTag:
            continue
    raise AuthError(f"sealed payload from {signer!r} does not open with this host's keys")


def new_sid() -> bytes:
    """A random 64-bit session id."""
    return secrets.token_bytes(SID_BYTES)


def _mac(
    key: bytes, kind: bytes, sid: bytes, signer: bytes, key_expr: bytes, payload: bytes, bind: bytes = b""
) -> bytes:
    msg = b"".join(
        (
            kind,
            sid,
            len(signer).to_bytes(1, "big"),
            signer,
            len(key_expr).to_bytes(2, "big"),
            key_expr,
            payload,
            bind,
        )
    )
    return hmac.digest(key, msg, "sha256")[:MAC_BYTES]


@dataclass
class Signer:
    """Signs what one process sends: its identity, key (and the send keys of its host's links)
    and session id."""

    identity: str
    key: bytes
    sid: bytes = field(default_factory=new_sid)
    links: tuple[bytes, ...] = ()  # Keyring.send_keys(): one more MAC per other host

    def __post_init__(self) -> None:
        self._id = self.identity.encode()
        self._head = MAGIC + self.sid + len(self._id).to_bytes(1, "big") + self._id
        self._keys = (self.key, *self.links)
        if len(self._keys) > MAX_MACS:
            raise ConfigError(f"at most {MAX_MACS - 1} links to other hosts")

    def attach(self, kind: bytes, key_expr: str, payload: bytes, *, bind: bytes = b"") -> bytes:
        """The attachment of ``payload`` sent as ``kind`` on ``key_expr``; ``bind`` (a reply: the
        query's attachment) is appended to the MAC input, so the reply verifies only for it."""
        ke = key_expr.encode()
        if len(self._keys) == 1:
            return self._head + _mac(self.key, kind, self.sid, self._id, ke, payload, bind)
        return self._head + b"".join(_mac(k, kind, self.sid, self._id, ke, payload, bind) for k in self._keys)


@dataclass(frozen=True, slots=True)
class Verified:
    """Who signed a message, and in which session."""

    signer: str
    sid: bytes


def parse(attachment: bytes | None) -> tuple[bytes, str, bytes]:
    """``(sid, signer, macs)`` of an attachment (``macs``: one or more MACs back to back);
    AuthError if it is missing or malformed."""
    if not attachment:
        raise AuthError("no authenticator (unsigned message)")
    a = attachment
    n = len(MAGIC) + SID_BYTES
    if len(a) < n + 1 + MAC_BYTES or a[: len(MAGIC)] != MAGIC:
        raise AuthError("malformed authenticator")
    ln = a[n]
    rest = len(a) - (n + 1 + ln)
    if rest < MAC_BYTES or rest % MAC_BYTES or rest > MAX_MACS * MAC_BYTES:
        raise AuthError("malformed authenticator")
    try:
        signer = a[n + 1 : n + 1 + ln].decode("ascii")
    except UnicodeDecodeError:
        raise AuthError("malformed authenticator (signer)") from None
    return a[len(MAGIC) : n], signer, a[n + 1 + ln :]


def verify(
    ring: Keyring, kind: bytes, key_expr: str, payload: bytes, attachment: bytes | None, *, bind: bytes = b""
) -> Verified:
    """Check ``attachment`` for ``payload`` sent as ``kind`` on ``key_expr`` (signed with ``bind``,
    see :meth:`Signer.attach`); AuthError if it fails."""
    sid, signer, macs = parse(attachment)
    key = ring.verifier(signer)
    if key is None:
        raise AuthError(f"unknown signer {signer!r}")
    want = _mac(key, kind, sid, signer.encode(), key_expr.encode(), payload, bind)
    if len(macs) == MAC_BYTES:
        ok = hmac.compare_digest(want, macs)
    else:
        ok = any(hmac.compare_digest(want, macs[i : i + MAC_BYTES]) for i in range(0, len(macs), MAC_BYTES))
    if not ok:
        raise AuthError(f"bad authenticator (claimed signer {signer!r})")
    return Verified(signer, sid)


def attachment_signer(attachment: bytes | None) -> str:
    """The claimed signer of an attachment, for reports ("?" if none can be read)."""
    try:
        return parse(attachment)[1]
    except AuthError:
        return "?"
