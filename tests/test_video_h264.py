"""H.264 video for distance (issue #41): the camera's encoder and bitrate control, and the picture
in the web console's page, decoded by Chromium's WebCodecs.

The unit tests check the encoder (PyAV/libx264) against PyAV's decoder, the keyframe detection,
the framing of the stream to the page and the bitrate control. The process test runs a site with
a real camera source (a 640×480, 25 fps clip through PyAV, as a capture card would deliver it), the
camera publishing H.264, and the web console serving it (``web.video = "h264"``); Chromium paints
it, and the test reads from the page what a surgeon sees: a moving picture, its rate and its age at
paint. A second page opened while the camera's periodic keyframe is a minute away shows the picture
at once (the console asks the camera for a keyframe). A frozen camera is flagged on the page.
Figures printed (``-s``); with
``TELESURG_PERF_DIR`` also written to ``video-h264.json`` there.
"""

from __future__ import annotations

import json
import os
import signal
import time
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from telesurg.shared.video import H264Encoder, RateControl, is_keyframe, pack, unpack

W, H = 640, 480


def _scene(i: int) -> np.ndarray:
    """Frame ``i`` of the test picture: colour fields changing every 25 frames, a white square
    crossing them (4 px a frame)."""
    colours = [(200, 40, 40), (40, 180, 60), (50, 70, 210)]
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:] = colours[(i // 25) % 3]
    x = (i * 4) % (W - 60)
    rgb[200:260, x : x + 60] = 255
    return rgb


def _decode_all(units: list[bytes]) -> list[np.ndarray]:
    import av

    ctx = av.CodecContext.create("h264", "r")
    out = []
    for u in units:  # (one access unit: one packet, as the page's decoder gets them)
        out += [f.to_ndarray(format="rgb24") for f in ctx.decode(av.Packet(u))]
    return out


def test_the_encoder_makes_one_decodable_unit_per_frame_and_keyframes_when_asked() -> None:
    enc = H264Encoder(W, H, 25.0, kbps=1500, keyframe_s=60.0)
    units, keys = [], []
    for i in range(30):
        if i == 17:
            enc.request_keyframe()
        data, key = enc.encode(_scene(i))
        units.append(data)
        keys.append(key)
    assert all(units), "a frame made no access unit (the encoder buffers: not zero latency)"
    assert [i for i, k in enumerate(keys) if k] == [0, 17]
    frames = _decode_all(units)
    assert len(frames) == 30
    for i in (0, 16, 29):  # the picture decoded is the picture encoded (lossy: colour within a few %)
        err = np.abs(frames[i].astype(int) - _scene(i).astype(int)).mean()
        assert err < 12, f"frame {i}: mean error {err:.1f}"
    enc.set_kbps(400)  # reopened at the new rate: the next frame starts a new stream
    data, key = enc.encode(_scene(30))
    assert key and is_keyframe(data)


def test_the_bitrate_follows_the_link() -> None:
    """Halved on the first loss or a growing age, held for hold_s, then raised step by step up to
    the maximum; never outside its range."""
    size = []

    rng = np.random.default_rng(1)
    noisy = [np.clip(_scene(i) + rng.normal(0, 40, (H, W, 3)), 0, 255).astype(np.uint8) for i in range(25)]

    def one_encoded_second(kbps: int) -> int:  # bytes of 25 frames of a busy picture at that rate
        enc = H264Encoder(W, H, 25.0, kbps=kbps)
        return sum(len(enc.encode(f)[0]) for f in noisy)

    for kbps in (300, 1500):
        size.append(one_encoded_second(kbps))
    print(
        f"one second of a busy picture: {size[0] * 8 / 1e3:.0f} kbit at 300, {size[1] * 8 / 1e3:.0f} at 1500"
    )
    assert size[0] < size[1] and size[0] * 8 / 1e3 < 300 * 1.5  # the cap holds (VBV)
    assert size[1] * 8 / 1e3 < 1500 * 1.5

    rc = RateControl(1500, 300, 2000)
    assert rc.update(0, 40.0, 0.0) == 1500 + rc.step_kbps  # calm: up (no cut yet)
    assert rc.update(2, 40.0, 1.0) == int(1600 * 0.7)  # a loss: cut
    assert rc.update(0, 40.0, 2.0) == 1120  # held after the cut
    assert rc.update(0, 40.0 + rc.age_margin_ms + 5, 3.2) == int(1120 * 0.7)  # the age grows: cut
    for t in range(20):
        k = rc.update(0, 40.0, 10.0 + t)
    assert k == 2000  # back up to the maximum, no higher
    for t in range(20):
        k = rc.update(5, 40.0, 40.0 + t)
    assert k == 300  # down to the minimum, no lower


def test_keyframes_and_the_page_framing() -> None:
    enc = H264Encoder(64, 48, 25.0, kbps=200)
    first, key = enc.encode(np.zeros((48, 64, 3), np.uint8))
    second, key2 = enc.encode(np.zeros((48, 64, 3), np.uint8))
    assert key and not key2 and is_keyframe(first) and not is_keyframe(second)
    assert not is_keyframe(b"") and not is_keyframe(b"\x00\x00\x01")
    packet = pack(first, True, 1.7e12 + 0.25, 42, 64, 48)
    assert unpack(packet) == (first, True, 1.7e12 + 0.25, 42, 64, 48)
    with pytest.raises(ValueError, match="header says"):
        unpack(packet[:-1])
    with pytest.raises(ValueError, match="even size"):
        H264Encoder(63, 48, 25.0, kbps=200)


def test_a_page_starts_at_a_keyframe_and_starts_over_after_a_missed_frame_or_a_backlog() -> None:
    from telesurg.shared.video import StreamGate

    g = StreamGate(backlog=3)
    assert not g.offer(b"d0", key=False, gap=False) and not g.queue  # joined mid-stream: waits
    g.offer(b"k1", key=True, gap=False)
    g.offer(b"d2", key=False, gap=False)
    assert list(g.queue) == [b"k1", b"d2"]
    g.queue.clear()  # (sent)
    g.offer(b"d4", key=False, gap=True)  # d3 never arrived: d4 would decode against nothing
    assert not g.queue and not g.synced and g.resets == 1
    g.offer(b"k5", key=True, gap=False)
    assert list(g.queue) == [b"k5"]
    g.offer(b"d6", key=False, gap=False)
    g.offer(b"d7", key=False, gap=False)  # the page reads nothing: three waiting
    assert g.offer(b"d8", key=False, gap=False)  # behind: dropped, and a keyframe is asked for
    assert not g.queue and g.resets == 2
    assert not g.offer(b"k9", key=True, gap=False) and list(g.queue) == [b"k9"]


def test_a_camera_with_bad_video_settings_is_refused() -> None:
    from telesurg.services.camera import CameraConfig
    from telesurg.shared.errors import ConfigError

    for bad, match in (
        ({"video": "vp9"}, "video 'vp9' invalid"),
        ({"video": "h264", "width": 321}, "even width"),
        ({"video": "h264", "video_kbps": 100_000, "video_max_kbps": 4000}, "video_kbps"),
        ({"video": "h264", "keyframe_s": 0.0}, "keyframe_s"),
    ):
        with pytest.raises(ConfigError, match=match):
            CameraConfig(**bad).validate()  # type: ignore[arg-type]


# --------------------------------------------------------------------------- in the page


def _make_clip(path: Path, n: int = 100) -> None:
    import av

    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=25)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        stream.time_base = Fraction(1, 25)
        for i in range(n):
            for pkt in stream.encode(av.VideoFrame.from_ndarray(_scene(i), format="rgb24")):
                out.mux(pkt)
        for pkt in stream.encode():
            out.mux(pkt)


@pytest.mark.process
@pytest.mark.skipif(not Path("/usr/bin/chromium").exists(), reason="needs /usr/bin/chromium")
def test_the_page_paints_the_h264_picture_and_a_new_page_gets_a_keyframe_at_once(tmp_path: Path) -> None:
    from conftest import wait_until
    from helpers import chromium
    from test_web_console import console_site, js

    clip = tmp_path / "clip.mp4"
    _make_clip(clip)
    camera = [
        "source='video'",
        f"url='{clip}'",
        f"width={W}",
        f"height={H}",
        "fps=25",
        "video='h264'",
        "keyframe_s=60",  # a page that joins waits for no periodic keyframe
    ]
    figures: dict[str, float] = {}
    overrides = {"camera": camera, "console": ["web.video='h264'"]}
    with (
        console_site(tmp_path, camera=True, overrides=overrides) as (url, _endpoint, _probe, site),
        chromium(url, tmp_path / "chromium") as (cdp, s),
    ):
        stats = (
            "window.telesurgH264 ? Object.assign(telesurgH264.stats(), {error: telesurgH264.error}) : null"
        )
        deadline = time.monotonic() + 60.0
        st = None
        while time.monotonic() < deadline:
            st = js(cdp, s, stats)
            if st and st["frames"] >= 60:
                break
            time.sleep(0.25)
        assert st and st["frames"] >= 60, f"the page painted no H.264 picture: {st}"
        assert not st["error"], st["error"]
        # the picture moves: the white square crosses the canvas (sampled along its row)
        row = (
            "(() => { const c = document.querySelector('#endoscope-h264');"
            " const d = c.getContext('2d').getImageData(0, 230, c.width, 1).data;"
            " let s = 0, n = 0;"
            " for (let x = 0; x < c.width; x++) if (d[4*x] > 230 && d[4*x+1] > 230) { s += x; n++; }"
            " return [c.width, c.height, n ? s / n : -1]; })()"
        )
        xs = []
        for _ in range(6):
            xs.append(js(cdp, s, row))
            time.sleep(0.15)
        assert xs[0][:2] == [W, H], f"canvas {xs[0][:2]}, the camera sends {W}x{H}"
        centres = [x[2] for x in xs if x[2] >= 0]
        assert len(set(round(c) for c in centres)) >= 3, f"the picture does not move: {xs}"
        info = js(cdp, s, "document.querySelector('#scope-info').textContent")
        assert "h264" in info and "painted" in info and "age at paint" in info, info
        time.sleep(2.0)
        st = js(cdp, s, stats)
        figures.update(fps=st["fps"], age_at_paint_p50_ms=round(st["age_p50"], 1))
        # a second page (a tab with the same session): its picture without waiting for the
        # camera's periodic keyframe, a minute away
        page = url.split("/login")[0] + "/"
        target = cdp.call("Target.createTarget", {"url": page})["targetId"]
        s2 = cdp.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        t0 = time.monotonic()
        second = None
        while time.monotonic() - t0 < 20.0:
            second = js(cdp, s2, stats)
            if second and second["frames"] >= 1:
                break
            time.sleep(0.1)
        assert second and second["frames"] >= 1, f"the second page shows nothing: {second}"
        figures["second_page_first_paint_s"] = round(time.monotonic() - t0, 2)
        # the camera freezes: the page says its picture is old; it thaws: the warning goes
        info = "document.querySelector('#scope-info').textContent"
        cam = site.pid("camera")
        os.kill(cam, signal.SIGSTOP)
        try:
            frozen = wait_until(lambda: "picture on screen" in str(js(cdp, s, info)), 10.0)
            said = str(js(cdp, s, info))
        finally:
            os.kill(cam, signal.SIGCONT)
        assert frozen, f"a frozen picture is not flagged: {said}"
        assert wait_until(lambda: "picture on screen" not in str(js(cdp, s, info)), 20.0), js(cdp, s, info)
    print(
        f"H.264 {W}x{H} in the page: {figures['fps']:.1f} fps painted, age at paint p50 "
        f"{figures['age_at_paint_p50_ms']} ms; a second page painted after "
        f"{figures['second_page_first_paint_s']} s"
    )
    if out := os.environ.get("TELESURG_PERF_DIR"):
        Path(out, "video-h264.json").write_text(json.dumps({"loopback": figures}, indent=2) + "\n")
