"""Every zenoh key expression, built from one prefix ``telesurg/<site>`` and CRTK stream names.

Layout under ``telesurg/<site>/`` (``<arm>``: an arm id such as ``arm1``; ``<service>``: a
service instance id)::

    master/<arm>/measured_cp     CartesianPose   master tip pose, master frame
    master/<arm>/measured_js     JointState      master joints (if the device has them)
    master/<arm>/buttons         MasterButtons   clutch pedal, operator presence
    slave/<arm>/servo_jp         JointSetpoint   joint setpoint from the mapping
    slave/<arm>/setpoint_cp      CartesianPose   Cartesian target behind servo_jp
    slave/<arm>/measured_js      JointState      slave joints
    slave/<arm>/measured_cp      CartesianPose   slave forceps-tip pose, base frame
    slave/<arm>/measured_cf      CartesianWrench external wrench at the tip, base frame (estimate)
    slave/<arm>/operating_state  OperatingState  slave state, mode, follow, hold reason
    slave/<arm>/setpoint_js      JointState      commanded joints of a slave-side motion (watchdog)
    slave/<arm>/scene            SceneState      the simulation's loose objects, their holders, collisions
    safety/<arm>/lease           SafetyLease     watchdog → slave permission to move
    safety/<arm>/state           SafetyState     watchdog's view of the arm
    safety/<arm>/video           VideoState      watchdog's view of the arm's video (frame age)
    camera/<cam>/image           CameraImage     encoded camera frames (<cam>: a camera id)
    camera/<cam>/measured_cp     CartesianPose   camera optical frame pose (x right, y down, z view), base
    camera/<cam>/servo_cp        CartesianPose   move the camera holder to this pose (same frame)
    estop                        EStop           e-stop / reset, from the console or any service
    slave/<arm>/command          (queryable)     Command → CommandReply (operator commands)
    mapping/<arm>/command        (queryable)     Command → CommandReply (scale; VIP set/reallocate)
    mapping/<arm>/teleop_state   TeleopState     teleop state of the pair driving slave <arm> (10 Hz,
                                                 on change; also a queryable: the current state)
    console/<m>/clutch           MasterButtons   the console's keyboard clutch for master <m>
    study/trial                  TrialState      the current trial of telesurg study: task, clock, score
    echo/<service>               (queryable)     replies at once: round-trip time across hosts
    events/<service>             SafetyEvent     events (transitions, IK failures, ...)
    heartbeat/<service>          Heartbeat       2 Hz service heartbeat
    alive/<service>/<sid>        (liveliness token; <sid>: the node's authenticated session id, hex)
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from telesurg.shared.errors import ConfigError

PREFIX_ROOT = "telesurg"
_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
_SID = re.compile(r"^[0-9a-f]{1,32}$")

MASTER_STREAMS = ("measured_cp", "measured_js", "buttons")
#: (``setpoint_js``: the slave's commanded joints while a slave-side motion drives the arm — PTP,
#: jog, playback, insert/remove, direct teach —, checked by the watchdog as it checks servo_jp)
SLAVE_STREAMS: tuple[str, ...] = (
    *("servo_jp", "setpoint_cp", "measured_js", "measured_cp", "measured_cf", "operating_state"),
    "setpoint_js",
    "scene",
)
SAFETY_STREAMS = ("lease", "state", "video")
CAMERA_STREAMS = ("image", "measured_cp", "servo_cp", "video", "video_feedback")
#: The mapping's streams, per *slave* arm: a slave is driven by one pair (one master may drive
#: several slaves, e.g. ``m1:arm1`` and ``m1:arm2``), so the slave arm names the pair (as for
#: ``mapping/<arm>/command``).
MAPPING_STREAMS = ("teleop_state",)


def check_id(kind: str, value: str) -> str:
    """Validate a site / arm / service id (letters, digits, ``_`` and ``-``, 1–64 chars)."""
    if not _ID.match(value):
        raise ConfigError(f"{kind} id {value!r} must match [A-Za-z0-9_-]{{1,64}}")
    return value


@dataclass(frozen=True)
class Keys:
    """Key expressions of one site. ``Keys("lab").slave("arm1", "servo_jp")``."""

    site: str = "local"

    def __post_init__(self) -> None:
        check_id("site", self.site)

    @property
    def prefix(self) -> str:
        """``telesurg/<site>``."""
        return f"{PREFIX_ROOT}/{self.site}"

    @property
    def all(self) -> str:
        """Everything of this site: ``telesurg/<site>/**``."""
        return f"{self.prefix}/**"

    def master(self, arm: str, stream: str) -> str:
        """``telesurg/<site>/master/<arm>/<stream>``; stream in :data:`MASTER_STREAMS`."""
        return self._arm_key("master", arm, stream, MASTER_STREAMS)

    def slave(self, arm: str, stream: str) -> str:
        """``telesurg/<site>/slave/<arm>/<stream>``; stream in :data:`SLAVE_STREAMS`."""
        return self._arm_key("slave", arm, stream, SLAVE_STREAMS)

    def safety(self, arm: str, stream: str) -> str:
        """``telesurg/<site>/safety/<arm>/<stream>``; stream in :data:`SAFETY_STREAMS`."""
        return self._arm_key("safety", arm, stream, SAFETY_STREAMS)

    def mapping(self, arm: str, stream: str) -> str:
        """``telesurg/<site>/mapping/<arm>/<stream>`` (``arm``: the pair's slave arm, or ``*``);
        stream in :data:`MAPPING_STREAMS`."""
        if arm == "*":
            if stream not in MAPPING_STREAMS:
                raise ConfigError(f"unknown mapping stream {stream!r}; valid: {', '.join(MAPPING_STREAMS)}")
            return f"{self.prefix}/mapping/*/{stream}"
        return self._arm_key("mapping", arm, stream, MAPPING_STREAMS)

    def camera(self, cam: str, stream: str) -> str:
        """``telesurg/<site>/camera/<cam>/<stream>``; stream in :data:`CAMERA_STREAMS`."""
        return self._arm_key("camera", cam, stream, CAMERA_STREAMS)

    @property
    def estop(self) -> str:
        """``telesurg/<site>/estop``: e-stop and reset commands for one or every arm."""
        return f"{self.prefix}/estop"

    def command(self, arm: str) -> str:
        """``telesurg/<site>/slave/<arm>/command``: the arm's command queryable."""
        return f"{self.prefix}/slave/{check_id('arm', arm)}/command"

    def echo(self, service: str = "*") -> str:
        """``telesurg/<site>/echo/<service>``: each service's echo queryable (RTT probes)."""
        return f"{self.prefix}/echo/{service if service == '*' else check_id('service', service)}"

    def console_clutch(self, master: str) -> str:
        """``telesurg/<site>/console/<master>/clutch``: the operator console's clutch for a master."""
        return f"{self.prefix}/console/{check_id('arm', master)}/clutch"

    @property
    def study_trial(self) -> str:
        """``telesurg/<site>/study/trial``: the current trial of ``telesurg study`` (the console shows it)."""
        return f"{self.prefix}/study/trial"

    def mapping_command(self, arm: str) -> str:
        """``telesurg/<site>/mapping/<arm>/command``: the mapping's command queryable (VIP)."""
        return f"{self.prefix}/mapping/{check_id('arm', arm)}/command"

    def events(self, service: str = "*") -> str:
        """``telesurg/<site>/events/<service>`` (``*`` matches every service)."""
        return f"{self.prefix}/events/{service if service == '*' else check_id('service', service)}"

    def heartbeat(self, service: str = "*") -> str:
        """``telesurg/<site>/heartbeat/<service>``."""
        svc = service if service == "*" else check_id("service", service)
        return f"{self.prefix}/heartbeat/{svc}"

    def alive(self, service: str = "*") -> str:
        """Liveliness key expression of ``service``'s tokens, ``telesurg/<site>/alive/<service>/*``
        (``*``: every service): what the launcher waits for and what presence watchers follow.
        A token itself is :meth:`alive_token`."""
        return f"{self.prefix}/alive/{service if service == '*' else check_id('service', service)}/*"

    def alive_token(self, service: str, sid: str) -> str:
        """The liveliness token of one node, ``telesurg/<site>/alive/<service>/<sid>``; ``sid``:
        its authenticated session id in hex (the ``sid`` its messages are signed with), so the
        token of the session whose messages a receiver authenticates is told apart from anyone
        else's token for the same service (zenoh merges tokens of one key)."""
        if not _SID.match(sid):
            raise ConfigError(f"liveliness sid {sid!r} must be 1-32 hex digits")
        return f"{self.prefix}/alive/{check_id('service', service)}/{sid}"

    def service_of_alive(self, key: str) -> str:
        """Service id from a liveliness key (inverse of :meth:`alive_token`)."""
        return self.parse_alive(key)[0]

    def parse_alive(self, key: str) -> tuple[str, str]:
        """``(service, sid)`` of a liveliness key (``sid`` "" for a key without one)."""
        rest = key.split("/alive/", 1)[-1].split("/")
        return rest[0], (rest[1] if len(rest) > 1 else "")

    def _arm_key(self, role: str, arm: str, stream: str, valid: tuple[str, ...]) -> str:
        if stream not in valid:
            raise ConfigError(f"unknown {role} stream {stream!r}; valid: {', '.join(valid)}")
        return f"{self.prefix}/{role}/{check_id('arm', arm)}/{stream}"
