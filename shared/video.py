"""Video for distance: an H.264 encoder for the camera, its bitrate control from the viewer's
feedback, and the framing of the stream to the browser.

The camera encodes each frame with libx264 (PyAV; ``ultrafast``, ``zerolatency``: no B-frames, no
lookahead, one frame in, one access unit out) under a VBV cap of one tenth of a second, so a frame
never waits behind a burst. A viewer (the web console) reports what arrives
(:class:`~telesurg.shared.messages.VideoFeedback`); :class:`RateControl` lowers the bitrate when
frames go missing or their age grows, and raises it again slowly while the link keeps up
(additive increase, multiplicative decrease). A viewer that lost a frame, or a page that just
opened, asks for a keyframe: the next frame is one.

Example::

    enc = H264Encoder(640, 480, 25.0, kbps=1500)
    data, key = enc.encode(rgb)            # one access unit (Annex B), keyframe or not
    rc = RateControl(1500, 300, 4000)
    kbps = rc.update(feedback, now)        # the bitrate to use now
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import numpy as np
import numpy.typing as npt

#: ``ultrafast`` / ``zerolatency``: one access unit per frame, at once (no lookahead, no B-frames)
X264_OPTIONS = {"preset": "ultrafast", "tune": "zerolatency", "bframes": "0", "repeat-headers": "1"}
#: s: the VBV buffer (the longest burst a frame may make), as a share of a second of bitrate
VBV_S = 0.1


def is_keyframe(data: bytes) -> bool:
    """Whether an H.264 access unit (Annex B) starts a picture a decoder can begin with: it holds an
    IDR slice (NAL type 5)."""
    i = 0
    n = len(data)
    while True:
        i = data.find(b"\x00\x00\x01", i)
        if i < 0 or i + 3 >= n:
            return False
        if data[i + 3] & 0x1F == 5:
            return True
        i += 3


class H264Encoder:
    """libx264 through PyAV: RGB frames in, Annex B access units out, one per frame."""

    def __init__(self, width: int, height: int, fps: float, kbps: int, keyframe_s: float = 2.0) -> None:
        if width % 2 or height % 2:
            raise ValueError(f"H.264 (yuv420p) needs an even size, got {width}x{height}")
        self.width, self.height, self.fps = width, height, fps
        self.keyframe_every = max(1, round(keyframe_s * fps))
        self.kbps = kbps
        self._ctx: Any = None
        self._pts = 0
        self._key_next = True
        self._open(kbps)

    def _open(self, kbps: int) -> None:
        import av

        ctx = av.CodecContext.create("libx264", "w")
        ctx.width, ctx.height, ctx.pix_fmt = self.width, self.height, "yuv420p"
        ctx.framerate = Fraction(self.fps).limit_denominator(1000)
        ctx.time_base = 1 / ctx.framerate
        ctx.bit_rate = kbps * 1000
        ctx.gop_size = self.keyframe_every
        vbv = max(1, round(kbps * VBV_S))
        ctx.options = {**X264_OPTIONS, "x264-params": f"vbv-maxrate={kbps}:vbv-bufsize={vbv}"}
        ctx.open()
        self._ctx, self.kbps, self._pts = ctx, kbps, 0
        self._key_next = True

    def set_kbps(self, kbps: int) -> None:
        """A new target bitrate: the encoder is reopened (its next frame is a keyframe)."""
        if kbps != self.kbps:
            self._open(kbps)

    def request_keyframe(self) -> None:
        """The next frame is a keyframe (a viewer lost one, or a new one joined)."""
        self._key_next = True

    def encode(self, rgb: npt.NDArray[np.uint8]) -> tuple[bytes, bool]:
        """One frame (``(h, w, 3)`` RGB) → its access unit and whether it is a keyframe."""
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        frame.pts = self._pts
        self._pts += 1
        if self._key_next:
            frame.pict_type = av.video.frame.PictureType.I
            self._key_next = False
        data = b"".join(bytes(p) for p in self._ctx.encode(frame))
        return data, is_keyframe(data)


@dataclass
class RateControl:
    """The camera's H.264 bitrate from the viewers' feedback: additive increase while frames arrive
    complete and young, multiplicative decrease on a loss or a growing age.

    Attributes:
        kbps: the current target.
        min_kbps, max_kbps: its range.
        age_margin_ms: a frame this much older than the youngest age seen is "late" (the link's
            queue is filling).
        step_kbps: the increase per calm feedback.
        cut: the factor on a loss or a late frame.
        hold_s: no increase for this long after a cut.
    """

    kbps: int
    min_kbps: int
    max_kbps: int
    age_margin_ms: float = 60.0
    step_kbps: int = 100
    cut: float = 0.7
    hold_s: float = 2.0
    _floor_ms: float = float("inf")
    _cut_at: float = float("-inf")

    def update(self, lost: int, age_p50_ms: float, now: float) -> int:
        """One feedback report (frames ``lost`` since the last, their median age) → the target."""
        if age_p50_ms > 0:
            self._floor_ms = min(self._floor_ms, age_p50_ms)
        late = age_p50_ms > self._floor_ms + self.age_margin_ms
        if lost > 0 or late:
            if now - self._cut_at >= 0.5:  # one cut per half second: the last cut shows first
                self.kbps = max(self.min_kbps, int(self.kbps * self.cut))
                self._cut_at = now
        elif now - self._cut_at >= self.hold_s:
            self.kbps = min(self.max_kbps, self.kbps + self.step_kbps)
        return self.kbps


# --------------------------------------------------------------------------- the stream to the page


class StreamGate:
    """One page's queue of access units. The page's decoder must start at a keyframe and never get
    a frame whose reference it missed: the gate passes nothing until a keyframe; a frame missing
    upstream (``gap``) or a page ``backlog`` packets behind empties the queue and waits for the next
    keyframe (:meth:`offer` says when to ask the camera for one)."""

    def __init__(self, backlog: int = 8) -> None:
        self.backlog = backlog
        self.queue: deque[bytes] = deque()
        self.synced = False
        self.resets = 0  # times the page started over at a keyframe

    def offer(self, packet: bytes, key: bool, gap: bool) -> bool:
        """One access unit arrived (``key``: a keyframe; ``gap``: frames before it are missing);
        True when the camera should be asked for a keyframe (the page fell behind)."""
        behind = len(self.queue) >= self.backlog
        if (gap or behind) and self.synced:
            self.synced = False
            self.queue.clear()
            self.resets += 1
        if not self.synced and not key:
            return behind  # (a gap: the relay asked already)
        self.synced = True
        self.queue.append(packet)
        return False


#: one packet to the page: length of what follows (u32), flags (u8: 1 keyframe), capture time on
#: the console's clock (f64, ms since the Unix epoch), frame sequence (u32), width, height (u16)
PACKET_HEAD = struct.Struct("<IBdIHH")


def pack(data: bytes, key: bool, capture_ms: float, seq: int, width: int, height: int) -> bytes:
    """One access unit framed for the page (``/video.h264``, read with ``fetch`` and decoded by
    WebCodecs)."""
    rest = PACKET_HEAD.size - 4 + len(data)
    head = PACKET_HEAD.pack(rest, 1 if key else 0, capture_ms, seq & 0xFFFFFFFF, width, height)
    return head + data


def unpack(buf: bytes) -> tuple[bytes, bool, float, int, int, int]:
    """:func:`pack` undone (tests): ``(data, key, capture_ms, seq, width, height)``."""
    rest, flags, capture_ms, seq, w, h = PACKET_HEAD.unpack_from(buf)
    if len(buf) != 4 + rest:
        raise ValueError(f"packet of {len(buf)} bytes, header says {4 + rest}")
    return buf[PACKET_HEAD.size :], bool(flags & 1), capture_ms, seq, w, h
