"""The web console's settings (``[console.web]`` of a site file; ``telesurg console --web``)."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from telesurg.shared.errors import ConfigError
from telesurg.shared.keys import check_id
from telesurg.shared.timing import check_rt_priority


@dataclass
class WebConfig:
    """The web console's own settings (``[console.web]``)."""

    host: str = "127.0.0.1"  # address the page is served on (0.0.0.0 for a phone on the LAN)
    # more names (no port) the page may be reached by, besides host, 127.0.0.1 and localhost: a
    # request with any other Host header is refused (DNS rebinding), e.g. ["192.168.1.20"] on a LAN
    allowed_hosts: list[str] = field(default_factory=list)
    session_s: float = 8 * 3600.0  # s: a login session lasts this long (then log in again)
    invite_s: float = 600.0  # s: a login link a page makes for another page is valid this long
    # s: a controlling page gone (no socket) this long may be replaced by a viewer's explicit take
    control_grace_s: float = 10.0
    port: int = 8470  # TCP port of the page and its websocket
    # service id of the node publishing the browser masters' streams: the mapping and the watchdog
    # accept master/<m>/* from this id only (their master_source); "" = no browser master (the
    # page shows the state and sends commands; another master_capture drives the slave)
    master_service: str = "master_capture"
    rate_hz: float = 200.0  # Hz: the newest browser sample is published at least this often
    buttons_hz: float = 50.0  # Hz: buttons go out on every change and at least this often
    # ms: a browser sample older than this is invalid (nothing published: the watchdog holds);
    # below the watchdog's master deadline (80 ms) so the console stops before the watchdog must
    sample_timeout_ms: float = 60.0
    state_hz: float = 20.0  # Hz: state pushed to every page
    # Hz: the predictive overlay (each arm's commanded tip over the endoscope picture) pushed to
    # every page while a camera publishes; 0: no overlay
    overlay_hz: float = 50.0
    # the endoscope picture to the page: "mjpeg" (camera/<cam>/image, any browser) or "h264"
    # (camera/<cam>/video, a camera with video = "h264": decoded by the page's WebCodecs; for a
    # distance, at a fraction of the bandwidth; docs/console.md)
    video: str = "mjpeg"
    max_frame_bytes: int = 4096  # a websocket frame larger than this is refused
    max_frames_hz: float = 400.0  # frames/s per connection on average (bursts of 100); more: refused
    max_rejects: int = 50  # refused frames after which a connection is closed as abusive
    mouse_mm_per_px: float = 0.2  # mm of master motion per dragged pixel (the page's mouse master)
    record_dir: str = "out/recordings"  # where record start puts its .mcap files
    # N: the tissue-force limit the page's force overlay marks and its gamepad rumble is scaled by
    # (full rumble at the limit); keep it equal to the watchdog's rules.tip_force.limit_n
    force_limit_n: float = 4.0
    # ms: a tip force (measured_cf, 500 Hz on the MH3F) older than this is stale: the overlay greys
    # and the rumble stops
    force_stale_ms: float = 100.0
    # SCHED_FIFO priority of the thread publishing the browser masters, 1-99 (0: the normal
    # scheduler), as master_capture's rt_priority; needs root or CAP_SYS_NICE
    rt_priority: int = 0

    def validate(self) -> None:
        """Raise ConfigError naming the problem."""
        if self.master_service:
            check_id("master_service", self.master_service)
        check_rt_priority(self.rt_priority)
        if not 60.0 <= self.session_s <= 7 * 86400.0:
            raise ConfigError(f"web.session_s={self.session_s} outside [60, 604800]")
        if not 10.0 <= self.invite_s <= 86400.0:
            raise ConfigError(f"web.invite_s={self.invite_s} outside [10, 86400]")
        if not 1.0 <= self.control_grace_s <= 3600.0:
            raise ConfigError(f"web.control_grace_s={self.control_grace_s} outside [1, 3600]")
        for h in self.allowed_hosts:
            if not re.fullmatch(r"[A-Za-z0-9.-]+|\[[0-9A-Fa-f:]+\]", h):
                raise ConfigError(f"web.allowed_hosts: {h!r} is not a host name (no port, no scheme)")
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"web.port={self.port} outside [0, 65535]")
        if not 100.0 <= self.rate_hz <= 2000.0:
            raise ConfigError(f"web.rate_hz={self.rate_hz} outside [100, 2000] (the issue asks >= 100 Hz)")
        if not 1.0 <= self.buttons_hz <= self.rate_hz:
            raise ConfigError(f"web.buttons_hz={self.buttons_hz} outside [1, rate_hz]")
        if not 10.0 <= self.sample_timeout_ms <= 1000.0:
            raise ConfigError(f"web.sample_timeout_ms={self.sample_timeout_ms} outside [10, 1000]")
        if not 1.0 <= self.state_hz <= 60.0:
            raise ConfigError(f"web.state_hz={self.state_hz} outside [1, 60]")
        if self.overlay_hz != 0.0 and not 5.0 <= self.overlay_hz <= 120.0:
            raise ConfigError(f"web.overlay_hz={self.overlay_hz} outside [5, 120] (0: no overlay)")
        if self.video not in ("mjpeg", "h264"):
            raise ConfigError(f"web.video={self.video!r} invalid; valid: 'mjpeg', 'h264'")
        if not 256 <= self.max_frame_bytes <= 1 << 20:
            raise ConfigError(f"web.max_frame_bytes={self.max_frame_bytes} outside [256, 1048576]")
        if not 10.0 <= self.max_frames_hz <= 10000.0:
            raise ConfigError(f"web.max_frames_hz={self.max_frames_hz} outside [10, 10000]")
        if self.max_rejects < 1:
            raise ConfigError("web.max_rejects must be >= 1")
        if not 0.1 <= self.force_limit_n <= 100.0:
            raise ConfigError(f"web.force_limit_n={self.force_limit_n} outside [0.1, 100] N")
        if not 10.0 <= self.force_stale_ms <= 5000.0:
            raise ConfigError(f"web.force_stale_ms={self.force_stale_ms} outside [10, 5000]")
        if not 0.01 <= self.mouse_mm_per_px <= 10.0:
            raise ConfigError(f"web.mouse_mm_per_px={self.mouse_mm_per_px} outside [0.01, 10]")
