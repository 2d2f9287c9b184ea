"""The ``policy`` master device: a learned (or scripted) policy moves the master, as a surgeon would.

The policy is a Python callable named ``module:function`` (or ``path/to/file.py:function``). With
``options`` set, ``function(**options)`` is called once and returns the policy. Every
``1 / rate_hz`` s the policy is given a :class:`PolicyObservation` — what the slave measures now
(``slave/<arm>/measured_js`` and ``measured_cp`` of the arm ``slave``, and whether it follows),
from the bus — and returns the master tip's displacement for this step (m, master frame, 3 values;
clipped to ``max_step_mm``, counted), optionally followed by the master's grip (a 4th value, 0 open …
1 closed: the slave's jaws follow it), or ``None``. Between calls the pose is held, sampled at
master_capture's rate.

It is an ordinary master: master_capture publishes its pose and buttons, the mapping clutches,
scales and maps it, the watchdog leases and watches it. Nothing of the safety chain is bypassed:

* a policy that returns ``None`` (or raises, or whose observations are older than ``stale_ms``)
  makes the reading invalid — nothing is published, the watchdog holds the arm after its master
  deadline, the mapping disengages; when it acts again the pedal is pressed anew ``repress_s``
  later (a new press: the engage rule);
* an e-stop stops the arm as for any master;
* ``clutch = "console"`` (supervised): only the operator's console clutch
  (``console/<m>/clutch``, the key ``telesurg console`` and the web console hold) engages; the
  operator lets the policy drive while holding it and takes control back by releasing it (the
  slave stops following at once). ``clutch = "policy"``: the pedal is pressed from ``press_at_s``
  while the policy acts (and, as for every device, the console clutch ORs with it).

Example (a site whose master is a policy, supervised from the console)::

    telesurg up --set master_capture.device=policy \\
        --set master_capture.device_options.policy=tests/policies/reach.py:make \\
        --set master_capture.device_options.clutch=console
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from telesurg.services.master_capture.devices import DeviceSample, MasterDevice, register
from telesurg.services.master_capture.devices.scripted import EngageRetry
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import CartesianPose, JointState, OperatingState, SceneState

if TYPE_CHECKING:
    from telesurg.shared.bus import Node

log = logging.getLogger(__name__)

CLUTCH_MODES = ("policy", "console")


@dataclass
class PolicyConfig:
    """``[master_capture.device_options]`` of the policy device."""

    policy: str = ""  # module:function or path/to/file.py:function (required)
    # keyword arguments: if any, function(**options) is called once and returns the policy
    options: dict[str, Any] = field(default_factory=dict)
    slave: str = "arm1"  # the slave arm whose measurements the policy observes
    slave_source: str = "slave_control"  # the only publisher of them accepted
    rate_hz: float = 30.0  # Hz: the policy is asked this often (the pose is held in between)
    max_step_mm: float = 5.0  # mm: a longer displacement per step is shortened (counted)
    # ms: observations older than this → the policy is not asked, nothing published (the watchdog
    # holds); the lease's lifetime, so a loaded host's stall does not drop the master
    stale_ms: float = 250.0
    # policy: the pedal is pressed while the policy acts, from press_at_s; console: only the
    # operator's console clutch engages (supervised: releasing it takes control back)
    clutch: str = "policy"
    press_at_s: float = 1.0  # s after start: the policy's pedal is pressed from then on
    repress_s: float = 0.5  # s: after the policy paused, its pedal is released this long, then pressed

    def validate(self) -> None:
        """Raise ConfigError naming the valid options."""
        if ":" not in self.policy:
            raise ConfigError(
                f"policy device: policy={self.policy!r} must be module:function or file.py:function"
            )
        if self.clutch not in CLUTCH_MODES:
            raise ConfigError(
                f"policy device: clutch {self.clutch!r} invalid; valid: {', '.join(CLUTCH_MODES)}"
            )
        if not 0.5 <= self.rate_hz <= 1000.0:
            raise ConfigError(f"policy device: rate_hz={self.rate_hz} outside [0.5, 1000]")
        if not 0.0 < self.max_step_mm <= 50.0:
            raise ConfigError(f"policy device: max_step_mm={self.max_step_mm} outside (0, 50]")
        if not 1.0 <= self.stale_ms <= 10_000.0:
            raise ConfigError(f"policy device: stale_ms={self.stale_ms} outside [1, 10000]")


@dataclass(frozen=True)
class PolicyObservation:
    """What the policy sees at one step.

    Attributes:
        t: s since the device started.
        joints: the slave arm's measured joints (rad / m), shape (n,).
        tip: its controlled point, m, the slave's base frame, shape (3,).
        tip_quat: its orientation, quaternion (x, y, z, w).
        following: the slave follows the master now (engaged).
        master: the master tip the device publishes, m, master frame, shape (3,).
        grip: the slave's jaws' commanded closure, 0 open … 1 closed (-1: no jaws).
        objects: the scene's loose objects (``slave/<arm>/scene``), name → position (m, base frame);
            empty without a scene.
        held_by: name → the arms whose jaws hold it now.
    """

    t: float
    joints: np.ndarray
    tip: np.ndarray
    tip_quat: tuple[float, float, float, float]
    following: bool
    master: np.ndarray
    grip: float = -1.0
    objects: dict[str, np.ndarray] = field(default_factory=dict)
    held_by: dict[str, tuple[str, ...]] = field(default_factory=dict)


Policy = Callable[[PolicyObservation], Sequence[float] | np.ndarray | None]


def load_policy(spec: str, options: dict[str, Any] | None = None) -> Policy:
    """The callable named ``module:function`` or ``file.py:function`` (made by
    ``function(**options)`` when ``options`` are given). ConfigError saying what is wrong."""
    where, _, name = spec.rpartition(":")
    try:
        if where.endswith(".py"):
            path = Path(where)
            if not path.is_file():
                raise ConfigError(f"policy file {path} not found")
            mod_spec = importlib.util.spec_from_file_location(f"telesurg_policy_{path.stem}", path)
            assert mod_spec is not None and mod_spec.loader is not None
            module = importlib.util.module_from_spec(mod_spec)
            mod_spec.loader.exec_module(module)
        else:
            module = importlib.import_module(where)
    except ConfigError:
        raise
    except Exception as e:
        raise ConfigError(f"policy {spec!r}: cannot load {where}: {type(e).__name__}: {e}") from e
    fn = getattr(module, name, None)
    if not callable(fn):
        raise ConfigError(f"policy {spec!r}: {where} has no callable {name!r}")
    policy = fn(**options) if options else fn
    if not callable(policy):
        raise ConfigError(f"policy {spec!r}: {name}(**options) did not return a callable")
    return policy  # type: ignore[no-any-return]


@register
class PolicyDevice(MasterDevice):
    """A policy as the master (see the module doc). ``connect(node)`` (master_capture calls it once
    its node is open) subscribes the observations."""

    name = "policy"
    config = PolicyConfig

    def __init__(self, cfg: PolicyConfig) -> None:
        cfg.validate()
        self.cfg = cfg
        self.policy: Policy | None = None
        self.position = np.zeros(3)
        self.engage_retry: EngageRetry | None = EngageRetry(1.0) if cfg.clutch == "policy" else None
        self.clipped = 0  # steps whose displacement was shortened to max_step_mm
        self.calls = 0  # times the policy was asked
        self._lock = threading.Lock()
        self._js: tuple[float, np.ndarray] | None = None  # (monotonic s received, joints)
        self._cp: tuple[float, np.ndarray, tuple[float, float, float, float]] | None = None
        self._following = False
        self._grip_seen = -1.0
        self._scene: SceneState | None = None
        self.grip = 0.0  # the master's grip the policy set, 0 open … 1 closed
        self._next = 0.0
        self._acting = False
        self._released_until = 0.0
        self._status = "waiting for the slave's measurements"
        self._failed = ""

    def __enter__(self) -> PolicyDevice:
        self.policy = load_policy(self.cfg.policy, self.cfg.options)
        log.info("policy %s at %.0f Hz, clutch %s", self.cfg.policy, self.cfg.rate_hz, self.cfg.clutch)
        return self

    def connect(self, node: Node) -> None:
        """Subscribe the slave's measurements (called by master_capture with its node)."""
        k, arm, src = node.keys, self.cfg.slave, [self.cfg.slave_source]
        node.subscribe(k.slave(arm, "measured_js"), JointState, self._on_js, sources=src)
        node.subscribe(k.slave(arm, "measured_cp"), CartesianPose, self._on_cp, sources=src)
        node.subscribe(k.slave(arm, "operating_state"), OperatingState, self._on_state, sources=src)
        node.subscribe(k.slave(arm, "scene"), SceneState, self._on_scene, sources=src)

    def _on_scene(self, m: SceneState, key: str) -> None:
        self._scene = m  # (one reference: set atomically)

    def _on_js(self, m: JointState, key: str) -> None:
        with self._lock:
            self._js = (time.monotonic(), np.array(m.position))

    def _on_cp(self, m: CartesianPose, key: str) -> None:
        with self._lock:
            self._cp = (time.monotonic(), np.array(m.position), m.orientation)

    def _on_state(self, m: OperatingState, key: str) -> None:
        with self._lock:
            self._following = m.follow
            self._grip_seen = m.grip

    def status(self) -> str:
        """Why nothing is published now (master_capture says it in its event)."""
        return self._status

    def observe(self, t: float) -> PolicyObservation | None:
        """The observation now, None if a measurement is missing or older than ``stale_ms``."""
        now, limit = time.monotonic(), self.cfg.stale_ms / 1e3
        with self._lock:
            js, cp, following = self._js, self._cp, self._following
        if js is None or cp is None:
            self._status = "stale: no measurements of the slave yet"
            return None
        age = now - min(js[0], cp[0])
        if age > limit:
            self._status = f"stale: the slave's measurements are {age * 1e3:.0f} ms old"
            return None
        objects: dict[str, np.ndarray] = {}
        held: dict[str, tuple[str, ...]] = {}
        if (sc := self._scene) is not None:
            for name in sc.objects:
                if (seen := sc.object(name)) is not None:
                    objects[name], held[name] = np.array(seen[0]), seen[1]
        return PolicyObservation(
            t, js[1], cp[1], cp[2], following, self.position.copy(), self._grip_seen, objects, held
        )  # fmt: skip

    def _act(self, obs: PolicyObservation | None) -> bool:
        """Ask the policy once; True if it acted (the pose moved or held by its word)."""
        if obs is None or self.policy is None:
            return False
        self.calls += 1
        try:
            out = self.policy(obs)
        except Exception as e:  # a broken policy holds the arm, said once per kind of failure
            why = f"{type(e).__name__}: {e}"
            if why != self._failed:
                log.error("policy raised %s: not publishing", why)
                self._failed = why
            self._status = f"refused: the policy raised {why}"
            return False
        if out is None:
            self._status = "paused: the policy returned None"
            return False
        d = np.array(out, dtype=float).reshape(-1)  # (a copy: the policy may keep its array)
        if d.shape not in ((3,), (4,)) or not np.all(np.isfinite(d)) or (len(d) == 4 and not 0 <= d[3] <= 1):
            self._status = f"refused: the policy returned {out!r}, not dx dy dz in m (and a grip 0–1)"
            return False
        if len(d) == 4:
            self.grip, d = float(d[3]), d[:3]
        n, lim = float(np.linalg.norm(d)), self.cfg.max_step_mm / 1e3
        if n > lim:
            d *= lim / n
            self.clipped += 1
            if self.clipped in (1, 10, 100) or self.clipped % 1000 == 0:
                log.warning(
                    "policy step %.1f mm shortened to %.1f mm (%d so far)", n * 1e3, lim * 1e3, self.clipped
                )
        self.position = self.position + d
        self._failed = self._status = ""
        return True

    def read(self, t: float) -> DeviceSample:
        if t >= self._next:
            self._next = max(self._next + 1.0 / self.cfg.rate_hz, t)
            acting = self._act(self.observe(t))
            if acting and not self._acting:
                self._released_until = t + self.cfg.repress_s if self.calls > 1 else 0.0
            self._acting = acting
        pedal = False
        if self.cfg.clutch == "policy" and self._acting:
            pedal = t >= self.cfg.press_at_s and t >= self._released_until
            if self.engage_retry is not None:
                pedal = self.engage_retry.clutch(pedal, t)
        p = self.position
        return DeviceSample(
            (float(p[0]), float(p[1]), float(p[2])),
            (0.0, 0.0, 0.0, 1.0),
            clutch=pedal,
            operator_present=True,
            valid=self._acting,
            grip=self.grip,
        )
