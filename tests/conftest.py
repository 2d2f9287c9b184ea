"""Shared fixtures: an in-process zenoh router on a free loopback port."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator

import pytest
from telesurg.services.common import gl_backend
from telesurg.services.launcher import free_port
from telesurg.shared.bus import BusConfig, open_session

# MuJoCo picks its OpenGL backend when it is first imported: the camera tests render offscreen in
# this process, after other tests imported mujoco (the camera service sets it itself)
os.environ.setdefault("MUJOCO_GL", gl_backend() or "egl")


@pytest.fixture
def endpoint() -> Iterator[str]:
    """``tcp/127.0.0.1:<port>`` of a zenoh router running in this process."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[ep]))
    try:
        yield ep
    finally:
        router.close()  # type: ignore[no-untyped-call]


def wait_until(pred: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Poll ``pred`` every 10 ms until true or ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return pred()
