"""Operator authority: who may send which operator command, e-stop or reset, and the two-step
confirmation of motion-starting commands. Pure logic (no bus): slave_control, the mapping and the
watchdog each hold one :class:`Authority` built from the site's ``[site.authority]`` table.

Rules (default deny for strangers; identity = the message header ``src``, authenticated once
message authentication is on, and across hosts the certificate CN the router's ACL checks):

* an **e-stop** is accepted from every source in ``estop_sources`` (``"*"``: any source — an
  e-stop is never refused, fail-safe);
* a **reset** of an e-stop only from an ``operators`` identity (the operator console), and only
  if it is stamped after the latest e-stop accepted (:meth:`Authority.estop_order`): an old reset
  sent again after anyone's newer e-stop never clears the latch;
* **read-only** commands (``public_commands``: ``state``, ``programs``) from anyone; **stopping**
  commands (``stop_commands``: ``stop``, ``abort``) from an operator or an e-stop source;
* **state-changing** commands that start no motion (``unconfirmed_commands``: teach, load a
  trocar, the scale commands) only from an operator, at once;
* **every other command** (PTP / posture adjustment, jog, insert / remove, playback, control-mode
  changes, VIP select / reallocate, a simulated push, and any command not listed — the safe
  default for a command added later) only from an operator *and* only after a confirmation:
  the first request is answered ``confirm required`` with a one-time token
  (:attr:`~telesurg.shared.messages.CommandReply.confirm`) and a summary; the same command with
  ``confirm=<token>`` added, from the same identity within ``confirm_s`` s, is carried out.

Example::

    auth = Authority(AuthorityConfig(operators=["console"]))
    verdict = auth.check(cmd)        # raises AuthorityError with the reason if refused
    if verdict.command is None:      # confirmation needed: answer with verdict.token
        ...
"""

from __future__ import annotations

import dataclasses
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from telesurg.shared.errors import AuthorityError, ConfigError
from telesurg.shared.messages import Command

#: the argument a confirmation adds to the command it confirms
CONFIRM_ARG = "confirm"
#: unconfirmed tokens kept at most (the oldest is dropped first): bounded memory under a flood
MAX_PENDING = 64


@dataclass
class AuthorityConfig:
    """Who may send which command (the site file's ``[site.authority]`` table)."""

    # service ids (message header src) of the operator console: the only identities that may reset
    # an e-stop or send a state-changing or motion-starting command
    operators: list[str] = field(default_factory=lambda: ["console"])
    # who may send an e-stop (and stop / abort): "*" = any source (fail-safe; with message
    # authentication on, any authenticated service)
    estop_sources: list[str] = field(default_factory=lambda: ["*"])
    # read-only commands anyone may send
    public_commands: list[str] = field(default_factory=lambda: ["state", "programs"])
    # commands that only stop a motion: from an operator or an e-stop source
    stop_commands: list[str] = field(default_factory=lambda: ["stop", "abort"])
    # operator commands carried out without a confirmation (they start no motion); every command
    # not listed here nor above needs the operator's confirmation
    unconfirmed_commands: list[str] = field(
        default_factory=lambda: [
            "teach_trocar",
            "teach_point",
            "clear_program",
            "load_trocar",
            "scale_up",
            "scale_down",
            "set_scale",
        ]
    )
    # s: a confirmation token is valid this long (0 = motion-starting commands need no confirmation)
    confirm_s: float = 5.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.confirm_s <= 60.0:
            raise ConfigError(f"authority.confirm_s={self.confirm_s} outside [0, 60]")
        if not self.estop_sources:
            raise ConfigError('authority.estop_sources is empty: nobody could stop the arm (use ["*"])')
        for name in ("operators", "estop_sources"):
            for s in getattr(self, name):
                if not s or (s != "*" and not s.replace("_", "").replace("-", "").isalnum()):
                    raise ConfigError(f'authority.{name}: {s!r} is not a service id (or "*")')


@dataclass(frozen=True)
class Verdict:
    """What to do with an authorised command.

    Attributes:
        command: the command to carry out (``confirm=`` removed), or None when a confirmation is
            needed first.
        token: the confirmation token (when ``command`` is None).
        reason: ``confirm required: …`` (when ``command`` is None), else "".
        kind: ``public``, ``stop``, ``operator`` or ``confirmed``.
    """

    command: Command | None
    token: str = ""
    reason: str = ""
    kind: str = ""


@dataclass
class _Pending:
    source: str
    arm: str
    name: str
    args: tuple[str, ...]
    expires: float


def _any(sources: list[str], src: str) -> bool:
    return "*" in sources or src in sources


def summary(cmd: Command) -> str:
    """``name args… on arm`` (what a confirmation prompt shows)."""
    args = " ".join(a for a in cmd.args if not a.startswith(f"{CONFIRM_ARG}="))
    return f"{cmd.name}{' ' + args if args else ''} on {cmd.arm}"


class Authority:
    """The authority table of one service plus its pending confirmations (thread-safe)."""

    def __init__(self, cfg: AuthorityConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self._clock = clock
        self._lock = threading.Lock()
        self._pending: OrderedDict[str, _Pending] = OrderedDict()
        self.refused = 0  # commands, e-stops and resets refused so far
        self._estop_ns = 0  # header stamp of the latest e-stop taken (the receiver's clock)

    # -- e-stop ---------------------------------------------------------------------------------
    def estop_problem(self, source: str, action: str) -> str:
        """Why an e-stop (``action`` ``estop``) or reset from ``source`` is refused ("" = allowed)."""
        if action == "estop":
            if _any(self.cfg.estop_sources, source):
                return ""
            problem = f"e-stop from {source!r} refused: not an e-stop source"
        elif source in self.cfg.operators:
            return ""
        else:
            problem = f"e-stop reset from {source!r} refused: only the operator console may reset"
        with self._lock:
            self.refused += 1
        return problem

    def estop_order(self, action: str, stamp_ns: int) -> str:
        """Order e-stops and resets by their header stamps (on this receiver's clock): an allowed
        e-stop is recorded (and always taken, ""); a reset stamped at or before the latest e-stop
        taken is refused (the reason; the caller counts it as a replay)."""
        with self._lock:
            if action == "estop":
                self._estop_ns = max(self._estop_ns, stamp_ns)
                return ""
            latest = self._estop_ns
            if stamp_ns > latest:
                return ""
            self.refused += 1
        return f"e-stop reset stamped {(latest - stamp_ns) / 1e9:.3f} s before the latest e-stop: not cleared"

    # -- commands -------------------------------------------------------------------------------
    def check(self, cmd: Command) -> Verdict:
        """Judge one operator command.

        Returns:
            a :class:`Verdict`: the command to carry out, or (``command`` None) a token to confirm.

        Raises:
            AuthorityError: the source may not send this command, or its confirmation is wrong or
                expired; the message is the reason.
        """
        cfg, src, name = self.cfg, cmd.header.source, cmd.name
        if name in cfg.public_commands:
            return Verdict(cmd, kind="public")
        if name in cfg.stop_commands and (src in cfg.operators or _any(cfg.estop_sources, src)):
            return Verdict(cmd, kind="stop")
        if src not in cfg.operators:
            self._refuse()
            raise AuthorityError(
                f"{name} from {src!r} refused: only the operator console "
                f"({', '.join(cfg.operators) or 'none configured'}) may send it"
            )
        if name in cfg.unconfirmed_commands or name in cfg.stop_commands or cfg.confirm_s <= 0.0:
            return Verdict(self._strip(cmd), kind="operator")
        token = cmd.arg_map().get(CONFIRM_ARG)
        stripped = self._strip(cmd)
        now = self._clock()
        with self._lock:
            for t in [t for t, p in self._pending.items() if p.expires < now - 60.0]:
                del self._pending[t]  # long expired: forget (an expired one is still named below)
            if token is None:
                new = secrets.token_hex(8)
                self._pending[new] = _Pending(src, cmd.arm, name, stripped.args, now + cfg.confirm_s)
                while len(self._pending) > MAX_PENDING:
                    self._pending.popitem(last=False)
                return Verdict(
                    None,
                    new,
                    f"confirm required: {summary(cmd)} (send it again with confirm=<token> "
                    f"within {cfg.confirm_s:g} s)",
                )
            p = self._pending.pop(token, None)
        if p is None:
            problem = "unknown or already used confirmation token"
        elif (p.source, p.arm, p.name, p.args) != (src, cmd.arm, name, stripped.args):
            problem = f"the token confirms {p.name} {' '.join(p.args)} on {p.arm} from {p.source!r}"
        elif now > p.expires:
            problem = f"confirmation {now - p.expires + cfg.confirm_s:.1f} s late (limit {cfg.confirm_s:g} s)"
        else:
            return Verdict(stripped, kind="confirmed")
        self._refuse()
        raise AuthorityError(f"{name} refused: {problem}")

    @property
    def pending(self) -> int:
        """Confirmation tokens issued and not yet used or dropped."""
        with self._lock:
            return len(self._pending)

    def _refuse(self) -> None:
        with self._lock:
            self.refused += 1

    @staticmethod
    def _strip(cmd: Command) -> Command:
        args = tuple(a for a in cmd.args if not a.startswith(f"{CONFIRM_ARG}="))
        return cmd if args == cmd.args else dataclasses.replace(cmd, args=args)
