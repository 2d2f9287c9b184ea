"""``telesurg bench viewer`` reads the viewer's time from rerun's encoded viewer state.

The bytes are built here in the wire layout rerun 0.41's web viewer answers
``window._handle.viewer_state()`` with (a ``GetStateResponse``: field 3 the active recording, its
field 2 per timeline (name, type, range {min, max}), its field 3 the active timeline (name, type,
{time})), captured from a live viewer while writing the bench.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from telesurg.tools.bench.viewer import fields, viewer_times


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _int(num: int, value: int) -> bytes:
    return _varint(num << 3) + _varint(value)


def _msg(num: int, body: bytes) -> bytes:
    return _varint(num << 3 | 2) + _varint(len(body)) + body


def _name(name: str) -> bytes:
    return _msg(1, _msg(1, name.encode()))


def _state(active: str, cursor: int, newest: dict[str, int]) -> bytes:
    rec = _msg(1, b"recording:telesurg:abc")
    for tl, hi in newest.items():
        rec += _msg(2, _name(tl) + _int(2, 3) + _msg(3, _int(1, hi - 10**9) + _int(2, hi)))
    rec += _msg(3, _name(active) + _int(2, 3) + _msg(3, _int(1, cursor)))
    return _msg(1, b"about:recording") + _msg(3, rec) + _msg(6, b"0.41.0")


def test_cursor_and_newest_times_are_read() -> None:
    t = 1_796_186_793_067_907_673
    state = _state("source_time", t - 5, {"source_time": t, "receive_time": t + 7})
    got = viewer_times(state)
    assert got == {
        "active": "source_time",
        "cursor_ns": t - 5,
        "newest_ns": {"source_time": t, "receive_time": t + 7},
    }


def test_a_viewer_without_data_has_no_cursor() -> None:
    assert viewer_times(_msg(1, b"about:welcome") + _msg(6, b"0.41.0")) == {
        "active": None,
        "cursor_ns": None,
        "newest_ns": {},
    }


def test_bytes_that_are_not_a_message_raise() -> None:
    with pytest.raises(ValueError):
        fields(b"\x0a\x10abc")  # a length-delimited field longer than the bytes
    with pytest.raises(ValueError):
        viewer_times(b"\x1a\x05\x0f\xff\xff\xff\xff")  # a recording whose body has wire type 7


def test_an_unknown_rasteriser_is_refused_by_name() -> None:
    from telesurg.tools.bench.browser import _flags

    with pytest.raises(ValueError, match="gl='gpu': one of swiftshader, llvmpipe"):
        _flags([], "gpu")


@pytest.mark.slow
@pytest.mark.parametrize(("gl", "renderer"), [("swiftshader", "SwiftShader"), ("llvmpipe", "llvmpipe")])
def test_the_bench_browser_draws_with_the_rasteriser_it_names(tmp_path: Path, gl: str, renderer: str) -> None:
    """What ``bench viewer --gl`` reports is what the page gets: a real headless Chromium asked for
    each rasteriser, the WebGL renderer string of a page read back (the figures in
    docs/performance.md compare the two)."""
    from telesurg.tools.bench.browser import CHROMIUM, chromium
    from telesurg.tools.bench.viewer import browser_version, webgl_renderer

    if not CHROMIUM.exists():
        pytest.skip(f"no Chromium at {CHROMIUM}")
    if gl == "llvmpipe" and not any(Path("/usr/lib").glob("*/dri/swrast_dri.so")):
        pytest.skip("no Mesa llvmpipe (libgl1-mesa-dri)")
    with chromium("about:blank", tmp_path, window=(320, 240), gl=gl) as (cdp, session):
        got = webgl_renderer(cdp, session)
        version = browser_version(cdp)
    assert got is not None and renderer in got, got
    # the build is named in every report: the same figures from another Chromium are not comparable
    installed = subprocess.run([str(CHROMIUM), "--version"], capture_output=True, text=True).stdout
    assert version.startswith("Chrome/") and version.removeprefix("Chrome/") in installed, (
        version,
        installed,
    )


@pytest.mark.slow
def test_the_bench_browser_runs_the_executable_it_is_given(tmp_path: Path) -> None:
    """``bench viewer --browser PATH`` (another Chromium build) is the executable that draws: a
    wrapper given as the browser leaves its mark and the page answers through it; a path with no
    executable is refused with exit code 2 before anything starts."""
    from telesurg.tools.bench.browser import CHROMIUM, chromium
    from telesurg.tools.bench.viewer import browser_version
    from telesurg.tools.bench.viewer import main as viewer_main

    missing = tmp_path / "no-such-chromium"
    assert viewer_main(["--seconds", "5", "--browser", str(missing)]) == 2
    if not CHROMIUM.exists():
        pytest.skip(f"no Chromium at {CHROMIUM}")
    mark = tmp_path / "ran"
    wrapper = tmp_path / "my-chromium"
    wrapper.write_text(f'#!/bin/sh\necho "$@" > {mark}\nexec {CHROMIUM} "$@"\n')
    wrapper.chmod(0o755)
    with chromium("about:blank", tmp_path, window=(320, 240), browser=wrapper) as (cdp, _):
        version = browser_version(cdp)
    assert version.startswith("Chrome/"), version
    assert "--remote-debugging-pipe" in mark.read_text()
