"""A new master device and a new safety rule, each from its own file (issue #40, acceptance 1).

``tests/devices/figure_eight.py`` registers a master device, ``tests/rules/tip_sphere.py`` a safety
rule; nothing else names them. The unit tests check the registries (an unknown name lists the known
ones; a rule that raises holds the arm). The process test starts one real site (router, watchdog,
slave_control with MuJoCo, mapping, master_capture) with both plugins (``SiteSpec.plugins``
→ every service's ``--plugin``): master_capture samples the figure-eight device, the slave follows
it, and the watchdog holds the arm with the rule's cause once the tip leaves its sphere.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from helpers import wait_first
from telesurg.services.launcher import CONTROL_SERVICES, Site, SiteSpec, free_port
from telesurg.services.master_capture import MasterCaptureConfig
from telesurg.services.master_capture import devices as master_devices
from telesurg.services.watchdog import WatchdogConfig
from telesurg.services.watchdog.logic import ArmSafety
from telesurg.services.watchdog.rules import ArmContext, Finding, Rule
from telesurg.shared import robots
from telesurg.shared.bus import BusConfig, Node
from telesurg.shared.errors import ConfigError
from telesurg.shared.messages import (
    CartesianPose,
    Header,
    JointSetpoint,
    MasterButtons,
    SafetyEvent,
    SafetyState,
)

HERE = Path(__file__).resolve().parent
FIGURE_EIGHT = HERE / "devices" / "figure_eight.py"
TIP_SPHERE = HERE / "rules" / "tip_sphere.py"
SCALE = 0.5  # the mapping's motion scale
RADIUS_MM = 40.0  # the figure-eight's half-width (master)
#: the sphere (slave): from any point of the scaled figure-eight the farthest is ≥ 20 mm away, so
#: the tip leaves a 12 mm sphere within one lap of the device
SPHERE_MM = 12.0
CAUSE = "tip left its sphere"


# -- registries (in-process) -----------------------------------------------------------------


def test_unknown_master_device_lists_the_known_ones() -> None:
    known = "valid: scripted, serial, spacemouse, touch, omega7, gamepad, policy, touch_sim"
    with pytest.raises(ConfigError, match=known):
        master_devices.open_device("phantom", MasterCaptureConfig())


def test_a_plugin_device_is_registered_and_reads_its_settings() -> None:
    robots.load_plugin(str(FIGURE_EIGHT))
    assert "figure_eight" in master_devices.names()
    cfg = MasterCaptureConfig(device="figure_eight", device_options={"radius_mm": 20.0, "period_s": 4.0})
    with master_devices.open_device(cfg.device, cfg) as dev:
        s = dev.read(1.0)  # a quarter lap: the lemniscate's tip at +x
        assert s.valid and s.clutch is False  # pressed only from press_at_s (2 s)
        assert s.position == pytest.approx((0.02, 0.0, 0.0), abs=1e-12)
        assert dev.read(2.5).clutch
    bad = MasterCaptureConfig(device="figure_eight", device_options={"radius": 20.0})
    with pytest.raises(ConfigError, match="radius_mm"):
        master_devices.open_device(bad.device, bad)


def test_unknown_rule_settings_name_the_known_rules() -> None:
    with pytest.raises(
        ConfigError, match="valid: joint_limits, workspace, joint_speed, rcm, operator_present, tip_force"
    ):
        WatchdogConfig(rules={"tip_spehre": {"radius_mm": 1.0}}).validate()
    with pytest.raises(ConfigError, match="modes"):
        WatchdogConfig(rules={"rcm": {"mode": ["trocar"]}}).validate()


class Broken(Rule):
    """A rule with a bug (not registered: added to one arm only)."""

    name = "broken"

    def on_servo(self, msg: JointSetpoint, now: float) -> Finding | None:
        raise ZeroDivisionError("division by zero")

    def check(self, now: float) -> Finding | None:
        return self.nonsense  # type: ignore[attr-defined,no-any-return]


def test_a_rule_that_raises_holds_the_arm() -> None:
    profile = robots.arm_profile("mh3f", "arm1")
    safety = ArmSafety("arm1", WatchdogConfig().policy(), profile.joint_names, tip_of=profile.tip)
    safety.on_buttons(MasterButtons(Header("master_capture", 1, 1), False, True), 0.0)
    assert safety.evaluate(0.0).state == "OK"
    safety.rules.append(Broken(ArmContext("arm1", safety.policy, safety.names, profile.tip), None))
    q = (0.0, 0.2, 0.3, 0.0, -0.6, 0.0)
    safety.on_servo(JointSetpoint(Header("mapping", 1, 1), profile.joint_names, q, True, 1), 0.0)
    v = safety.evaluate(0.0)
    assert v.state == "HOLD"
    assert any("safety rule broken failed: ZeroDivisionError" in c for c in v.causes), v.causes
    assert any("safety rule broken failed: AttributeError" in c for c in v.causes), v.causes


def test_the_manual_quotes_the_plugin_files_as_they_are() -> None:
    """docs/extending.md's worked examples are these files, as tested here."""
    doc = (HERE.parent / "docs" / "extending.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", doc, re.S)
    assert FIGURE_EIGHT.read_text() in blocks
    assert TIP_SPHERE.read_text() in blocks


# -- one real site with both plugins ----------------------------------------------------------


@dataclass
class Log:
    lock: threading.Lock = field(default_factory=threading.Lock)
    master: dict[int, np.ndarray] = field(default_factory=dict)  # master stamp ns → position
    setpoints: list[tuple[float, np.ndarray, bool, int]] = field(default_factory=list)  # t, q, follow, origin
    tip: list[tuple[float, np.ndarray]] = field(default_factory=list)  # slave measured_cp
    safety: list[tuple[float, str, tuple[str, ...], float]] = field(
        default_factory=list
    )  # t, state, causes, scale
    events: list[tuple[float, str, str, str]] = field(default_factory=list)  # t, source, kind, text


@pytest.fixture(scope="module")
def site_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Log, float, float, dict[str, int]]]:
    out = tmp_path_factory.mktemp("plugins")
    spec = SiteSpec(
        port=free_port(),
        config_dir=None,
        services=tuple(s for s in CONTROL_SERVICES if s != "mirror"),  # nothing to draw here
        overrides={
            "master_capture": [
                "device=figure_eight",
                "rate_hz=100.0",
                f"device_options.radius_mm={RADIUS_MM}",
                "device_options.period_s=10.0",
            ],
            "mapping": [f"scale={SCALE}"],
            "watchdog": [f"rules.tip_sphere.radius_mm={SPHERE_MM}"],
        },
        log_dir=out / "logs",
        plugins=(str(FIGURE_EIGHT), str(TIP_SPHERE)),
    )
    log = Log()
    try:
        with Site(spec) as site, Node(BusConfig(connect=[spec.endpoint]), "local", "plugin_probe") as node:
            k = node.keys

            def on_master(m: CartesianPose, key: str) -> None:
                with log.lock:
                    log.master[m.header.stamp_ns] = np.array(m.position)

            def on_sp(m: JointSetpoint, key: str) -> None:
                with log.lock:
                    log.setpoints.append((time.monotonic(), np.array(m.position), m.follow, m.origin_ns))

            def on_tip(m: CartesianPose, key: str) -> None:
                with log.lock:
                    log.tip.append((time.monotonic(), np.array(m.position)))

            def on_safety(m: SafetyState, key: str) -> None:
                with log.lock:
                    log.safety.append((time.monotonic(), m.state, m.causes, m.scale))

            def on_event(m: SafetyEvent, key: str) -> None:
                with log.lock:
                    log.events.append((time.monotonic(), m.header.source, m.kind, m.text))

            node.subscribe(k.master("m1", "measured_cp"), CartesianPose, on_master)
            node.subscribe(k.slave("arm1", "servo_jp"), JointSetpoint, on_sp)
            node.subscribe(k.slave("arm1", "measured_cp"), CartesianPose, on_tip)
            node.subscribe(k.safety("arm1", "state"), SafetyState, on_safety)
            node.subscribe(k.events(), SafetyEvent, on_event)

            t_engage = wait_first(
                log.lock, site, lambda: next((t for t, _, f, _ in log.setpoints if f), None), 60.0
            )
            assert t_engage is not None, "the mapping never engaged on the plugin device"
            t_hold = wait_first(
                log.lock,
                site,
                lambda: next(
                    (t for t, s, c, _ in log.safety if t > t_engage and s == "HOLD" and CAUSE in " ".join(c)),
                    None,
                ),
                25.0,
            )
            assert t_hold is not None, "the watchdog never held with the plugin rule's cause"
            time.sleep(2.0)  # the master moves on; the slave must not
            codes = site.stop()
    finally:
        for f in sorted((out / "logs").glob("*.log")):
            print(f"--- {f.name}\n{f.read_text()[-3000:]}")
    yield log, t_engage, t_hold, codes


@pytest.mark.process
def test_the_slave_follows_the_plugin_device(site_run: tuple[Log, float, float, dict[str, int]]) -> None:
    log, t_engage, t_hold, codes = site_run
    tip_of = robots.arm_profile("mh3f", "arm1").tip
    follow = [(t, q, o) for t, q, f, o in log.setpoints if f and t < t_hold]
    assert len(follow) > 50, f"only {len(follow)} followed setpoints"
    # every followed setpoint moves the tip by the scaled master increment since the one before
    # (paired by the master sample's stamp; a DEGRADED watchdog scales it further)
    factors = sorted({SCALE * s for *_, s in log.safety} | {SCALE})
    pairs = [(a, b) for a, b in pairwise(follow) if a[2] in log.master and b[2] in log.master]
    assert len(pairs) > 0.9 * len(follow)
    err = []
    for (_, qa, oa), (_, qb, ob) in pairs:
        d_tip = float(np.linalg.norm(tip_of(qb) - tip_of(qa)))
        d_m = float(np.linalg.norm(log.master[ob] - log.master[oa]))
        if d_tip < 1e-6:
            continue  # a re-anchor (the watchdog's scale changed) or a repeated setpoint
        err.append(min(abs(d_tip - k * d_m) for k in factors))
    print(f"setpoint tip vs scaled master increments: max {max(err) * 1e3:.4f} mm over {len(err)} steps")
    assert len(err) > 0.8 * len(pairs)
    assert max(err) < 1e-4  # 0.1 mm a step
    # the MuJoCo tip moved with it
    meas = np.array([p for t, p in log.tip if t_engage <= t <= t_hold])
    travel = float(np.linalg.norm(meas - meas[0], axis=1).max()) * 1e3
    print(f"measured tip travel while following: {travel:.1f} mm")
    assert travel > 0.5 * SPHERE_MM
    assert all(c == 0 for c in codes.values()), codes


@pytest.mark.process
def test_the_watchdog_holds_with_the_plugin_rules_cause(
    site_run: tuple[Log, float, float, dict[str, int]],
) -> None:
    log, _, t_hold, _ = site_run
    transitions = [text for t, s, k, text in log.events if s == "watchdog" and k == "safety_transition"]
    assert any("→ HOLD" in text and CAUSE in text for text in transitions), transitions
    # the tip stops where the rule held it: a little past the sphere, not along the figure-eight
    centre = next(p for t, p in log.tip if t >= min(t for t, _, f, _ in log.setpoints if f))
    after = np.array([p for t, p in log.tip if t >= t_hold + 0.3])
    assert len(after) > 20
    out_mm = float(np.linalg.norm(after - centre, axis=1).max()) * 1e3
    moved_mm = float(np.linalg.norm(after - after[0], axis=1).max()) * 1e3
    print(f"after the hold: the slave moved {moved_mm:.3f} mm, at most {out_mm:.1f} mm from the centre")
    assert moved_mm < 0.5
    assert out_mm < SPHERE_MM + 5.0
    assert not any(f for t, _, f, _ in log.setpoints if t > t_hold + 0.5)  # no follow since
