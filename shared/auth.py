"""Per-service message authentication: a site keyring, HMAC-SHA256 authenticators in the zenoh
attachment, per-process session ids.

**Keyring.** A directory (mode 0700) with one file per identity, ``<identity>.key`` (mode 0600,
the 32-byte key in hex, from :mod:`secrets`). An identity is a service instance id (the header
``src`` it publishes under: ``watchdog``, ``mapping``, ``console``, …). ``telesurg keys init DIR``
makes one; ``telesurg up`` / ``demo`` make the default one if it is absent; every process loads
it (:func:`default_keys_dir`; ``--keyring DIR`` on every command line, ``--keys DIR`` for
``up`` / ``demo``; ``BusConfig.keys_dir``). Nothing secret is in the repository. A process
whose own identity has no key yet adds one to a keyring it can write (:meth:`Keyring.ensure`):
anyone who can write the keyring can read every key in it anyway.
Receivers look a signer they do not know up in the directory again, at most every 0.25 s per
name (a key added after they started).

**Authenticator.** Every publication, query and reply made through :class:`~telesurg.shared.bus.Node`
carries, in the zenoh *attachment* (the msgpack payload is unchanged)::

    b"T1" | sid (8 bytes) | len(signer) (1 byte) | signer (ASCII) | mac (16 bytes)

``mac`` = HMAC-SHA256(key[signer], kind | sid | len(signer) | signer | len(key_expr) (2 bytes,
big-endian) | key_expr | payload), truncated to 16 bytes; ``kind`` is ``P`` (put), ``Q`` (query)
or ``R`` (reply). So a message cannot be moved to another key expression, turned from a
publication into a command, or claimed by another signer. ``sid`` is a random 64-bit session id
per process (per :class:`Signer`): a restarted publisher is recognised by a new authenticated
``sid`` (``shared/streams.py``), never by its sequence number going back to 0. The receiver also
requires the signer to equal the decoded header ``src`` (checked in the bus).

Ed25519 (``cryptography``) was measured beside HMAC for the 1 kHz path: see docs/security.md.
"""

from __future__ import annotations

import hmac
import logging
import os
import re
import secrets
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path

from telesurg.shared.errors import ConfigError, MessageError

log = logging.getLogger(__name__)

MAGIC = b"T1"
SID_BYTES = 8
MAC_BYTES = 16
KEY_BYTES = 32
KEY_SUFFIX = ".key"
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


def _check_identity(identity: str) -> str:
    if not _ID.match(identity):
        raise ConfigError(f"key identity {identity!r} must match [A-Za-z0-9_-]{{1,64}}")
    return identity


def _read_key(path: Path) -> bytes:
    st = path.stat()
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ConfigError(
            f"key file {path} is readable by others (mode {st.st_mode & 0o777:o}); chmod 600 it"
        )
    try:
        key = bytes.fromhex(path.read_text().strip())
    except ValueError:
        raise ConfigError(f"key file {path}: not a hex key") from None
    if len(key) != KEY_BYTES:
        raise ConfigError(f"key file {path}: {len(key)} bytes, expected {KEY_BYTES}")
    return key


def write_key(directory: Path, identity: str, key: bytes | None = None) -> bool:
    """Write ``identity``'s key (new random one unless given) into ``directory``, mode 0600.

    Returns False (and leaves the file alone) when the identity already has a key."""
    _check_identity(identity)
    key = key if key is not None else secrets.token_bytes(KEY_BYTES)
    if len(key) != KEY_BYTES:
        raise ConfigError(f"key of {identity}: {len(key)} bytes, expected {KEY_BYTES}")
    path = directory / f"{identity}{KEY_SUFFIX}"
    if path.exists():
        return False
    # written whole under a temporary name, then linked into place (fails if the name exists):
    # a reader never sees a half-written key, and two processes adding one identity agree
    tmp = directory / f".{identity}.{secrets.token_hex(8)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(key.hex() + "\n")
        os.link(tmp, path)
    except FileExistsError:
        return False
    finally:
        tmp.unlink(missing_ok=True)
    return True


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
    """The keys of a site, loaded from a keyring directory."""

    path: Path
    keys: dict[str, bytes] = field(default_factory=dict)
    _missed: dict[str, float] = field(default_factory=dict)  # unknown signer -> last look-up (monotonic s)

    @classmethod
    def load(cls, directory: str | Path) -> Keyring:
        """Load every ``*.key`` of ``directory``; ConfigError (saying how to make one) if absent."""
        d = Path(directory)
        if not d.is_dir():
            raise ConfigError(
                f"no keyring at {d}: make one with `telesurg keys init {d}` "
                "(telesurg up / demo make the default one), or pass --keyring DIR"
            )
        ring = cls(d)
        for p in sorted(d.glob(f"*{KEY_SUFFIX}")):
            ring.keys[p.name[: -len(KEY_SUFFIX)]] = _read_key(p)
        return ring

    def identities(self) -> list[str]:
        """Known identities, sorted."""
        return sorted(self.keys)

    def key(self, identity: str) -> bytes | None:
        """``identity``'s key; an unknown one is looked up on disk at most every
        :data:`LOOKUP_INTERVAL_S`."""
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
        try:
            k = _read_key(p)
        except (OSError, ConfigError):
            return None
        self.keys[identity] = k
        self._missed.pop(identity, None)
        return k

    def ensure(self, identity: str) -> bytes:
        """``identity``'s key, added to the keyring directory if it has none (and it is writable)."""
        k = self.key(identity) or self.keys.get(identity)
        if k is not None:
            return k
        p = self.path / f"{identity}{KEY_SUFFIX}"
        try:
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
    """Signs what one process sends: its identity, key and session id."""

    identity: str
    key: bytes
    sid: bytes = field(default_factory=new_sid)

    def __post_init__(self) -> None:
        self._id = self.identity.encode()
        self._head = MAGIC + self.sid + len(self._id).to_bytes(1, "big") + self._id

    def attach(self, kind: bytes, key_expr: str, payload: bytes, *, bind: bytes = b"") -> bytes:
        """The attachment of ``payload`` sent as ``kind`` on ``key_expr``; ``bind`` (a reply: the
        query's attachment) is appended to the MAC input, so the reply verifies only for it."""
        return self._head + _mac(self.key, kind, self.sid, self._id, key_expr.encode(), payload, bind)


@dataclass(frozen=True, slots=True)
class Verified:
    """Who signed a message, and in which session."""

    signer: str
    sid: bytes


def parse(attachment: bytes | None) -> tuple[bytes, str, bytes]:
    """``(sid, signer, mac)`` of an attachment; AuthError if it is missing or malformed."""
    if not attachment:
        raise AuthError("no authenticator (unsigned message)")
    a = attachment
    n = len(MAGIC) + SID_BYTES
    if len(a) < n + 1 + MAC_BYTES or a[: len(MAGIC)] != MAGIC:
        raise AuthError("malformed authenticator")
    ln = a[n]
    if len(a) != n + 1 + ln + MAC_BYTES:
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
    sid, signer, mac = parse(attachment)
    key = ring.key(signer)
    if key is None:
        raise AuthError(f"unknown signer {signer!r}")
    want = _mac(key, kind, sid, signer.encode(), key_expr.encode(), payload, bind)
    if not hmac.compare_digest(want, mac):
        raise AuthError(f"bad authenticator (claimed signer {signer!r})")
    return Verified(signer, sid)


def attachment_signer(attachment: bytes | None) -> str:
    """The claimed signer of an attachment, for reports ("?" if none can be read)."""
    try:
        return parse(attachment)[1]
    except AuthError:
        return "?"
