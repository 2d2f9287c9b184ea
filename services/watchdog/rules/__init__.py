"""Safety rules: the checks the watchdog runs on each arm, one small class per rule, one file each.

A rule subclasses :class:`Rule`, names itself (``name``), states the ``cause`` text it reports,
takes the inputs it needs by overriding ``on_servo`` (``slave/<arm>/servo_jp``), ``on_slave_state``
(``slave/<arm>/operating_state``), ``on_buttons`` (``master/<m>/buttons``) or ``on_wrench``
(``slave/<arm>/measured_cf``, the tip wrench), and is registered with
:func:`register`. The verdict:

* a :class:`Finding` returned by an input method is a message-level fault: the arm holds (or runs
  DEGRADED) for ``fault_latch_ms`` after the last offending message;
* a :class:`Finding` returned by :meth:`Rule.check` (every lease tick) holds while it is returned;
* ``None`` is ok. A rule that raises holds the arm with the error as the cause.

A rule's settings are its ``config`` dataclass, from the watchdog table ``[watchdog.rules.<name>]``
(``--set rules.<name>.<key>=…``); the built-in rules read the watchdog's own limits from the arm's
``policy`` (:class:`~telesurg.services.watchdog.logic.Policy`). A plugin file (``--plugin FILE``)
registers more. ``docs/extending.md``, "Add a safety rule".

Example::

    @register
    class NoReverse(Rule):
        name = "no_reverse"
        cause = "joint 1 below 0"

        def on_servo(self, msg: JointSetpoint, now: float) -> Finding | None:
            return Finding(HOLD, self.cause) if msg.position[0] < 0 else None
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

import numpy as np
from telesurg.shared.config import from_dict
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import CartesianWrench, JointSetpoint, MasterButtons, OperatingState

if TYPE_CHECKING:
    from telesurg.services.watchdog.logic import Policy

HOLD = "HOLD"
DEGRADED = "DEGRADED"


@dataclass(frozen=True)
class Finding:
    """A rule's verdict other than ok: ``state`` HOLD or DEGRADED, with its ``cause`` (text).

    ``tag`` names the latch slot and the fault counter of a message-level fault ("" = the rule's
    name): a rule with two kinds of fault gives them two tags.
    """

    state: str
    cause: str
    tag: str = ""


@dataclass(frozen=True)
class ArmContext:
    """What a rule knows of its arm: ``arm`` id, ``policy`` (the watchdog's limits for it),
    ``names`` (its joint names, servo_jp order), ``tip_of`` (forward kinematics: q → tip
    position, m, base frame; None if the robot has none)."""

    arm: str
    policy: Policy
    names: tuple[str, ...]
    tip_of: Callable[[np.ndarray], np.ndarray] | None = None


@dataclass
class NoSettings:
    """A rule without settings of its own."""


class Rule:
    """Base class of a safety rule (see the module doc); every input is ok unless overridden."""

    name: ClassVar[str]
    cause: ClassVar[str] = ""
    config: ClassVar[type[Any]] = NoSettings

    def __init__(self, arm: ArmContext, cfg: Any) -> None:
        self.arm = arm
        self.cfg = cfg

    def on_servo(self, msg: JointSetpoint, now: float) -> Finding | None:
        """One joint setpoint (its joint names are the arm's); ``now``: monotonic s."""
        return None

    def on_slave_state(self, msg: OperatingState, now: float) -> Finding | None:
        """One slave operating state."""
        return None

    def on_buttons(self, msg: MasterButtons, now: float) -> Finding | None:
        """One master buttons message."""
        return None

    def on_wrench(self, msg: CartesianWrench, now: float) -> Finding | None:
        """One slave tip wrench (``measured_cf``: what the tissue exerts on the instrument)."""
        return None

    def check(self, now: float) -> Finding | None:
        """At every lease tick: a level verdict (holds while returned)."""
        return None


R = TypeVar("R", bound=type[Rule])
_RULES: dict[str, type[Rule]] = {}


def register(cls: R) -> R:
    """Register a rule class under ``cls.name`` (a class decorator)."""
    name = getattr(cls, "name", "")
    if not isinstance(name, str) or not name.isidentifier():
        raise ConfigError(f"safety rule class {cls.__name__}: name {name!r} must be an identifier")
    old = _RULES.get(name)
    if old is not None and old is not cls:
        raise ConfigError(f"safety rule {name!r} already registered by {old.__module__}.{old.__name__}")
    _RULES[name] = cls
    return cls


def names() -> tuple[str, ...]:
    """The registered rule names, in the order the watchdog runs them (built-in first)."""
    return tuple(_RULES)


def get(name: str) -> type[Rule]:
    """The rule class registered as ``name``; ConfigError listing the known names if none."""
    try:
        return _RULES[name]
    except KeyError:
        raise ConfigError(
            f"safety rule {name!r} unknown; valid: {', '.join(names())} (more from --plugin FILE)"
        ) from None


def check_settings(settings: dict[str, dict[str, Any]]) -> None:
    """ConfigError if ``settings`` (``[watchdog.rules]``) names an unknown rule or key."""
    for name, table in settings.items():
        cls = get(name)
        if not isinstance(table, dict):
            raise ConfigError(f"rules.{name} must be a table, got {table!r}")
        from_dict(cls.config, table, f"rules.{name}")


def make_rules(arm: ArmContext, settings: dict[str, dict[str, Any]] | None = None) -> list[Rule]:
    """One instance of every registered rule for ``arm``, with its settings from ``settings``."""
    settings = settings or {}
    check_settings(settings)
    return [cls(arm, from_dict(cls.config, settings.get(n, {}), f"rules.{n}")) for n, cls in _RULES.items()]


#: the built-in rules, one module each (importing one registers it), in the order they run
BUILT_IN = ("joint_limits", "workspace", "joint_speed", "rcm", "operator_present", "tip_force")
for _module in BUILT_IN:
    importlib.import_module(f"{__name__}.{_module}")
