"""The device end of a serial line, shared by the emulated encoder board and servo controller.

A pseudo-terminal pair stands in for the USB serial port: the emulator holds the controller
side, the host opens the device side by its path (printed on stdout).
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from telesurg.shared.serial_link import Frame, FrameReader
from telesurg.shared.timing import CycleTimer

#: Bytes the emulator keeps for a host that does not read; beyond that the backlog is dropped
#: (the host resynchronises on the next 0x00, as with a real board's full USB buffer).
MAX_PENDING_BYTES = 4096


class DevicePort:
    """Non-blocking frame reads and buffered writes on the device's file descriptor ``fd``.

    Attributes:
        reader: the frame reader (its ``errors`` count the corrupt frames from the host).
    """

    def __init__(self, fd: int) -> None:
        self.fd = fd
        os.set_blocking(fd, False)
        self.reader = FrameReader()
        self._out = bytearray()

    def read_frames(self) -> list[Frame]:
        """The complete frames the host has written since the last call (none if it is not there)."""
        try:
            data = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError:  # EIO: no process has the pty's device side open (between host connections)
            return []
        return self.reader.feed(data)

    def write(self, data: bytes) -> int:
        """Write ``data`` after whatever is still pending; return the bytes dropped (0 normally):
        with more than :data:`MAX_PENDING_BYTES` pending, nobody reads and the backlog goes."""
        self._out += data
        try:
            n = os.write(self.fd, self._out)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError:  # EIO: the device side is closed
            n = len(self._out)
        del self._out[:n]
        if len(self._out) > MAX_PENDING_BYTES:
            dropped = len(self._out)
            self._out.clear()
            return dropped
        return 0


def serve_at(rate_hz: float, step: Callable[[], None], stop: threading.Event, seconds: float = 0.0) -> None:
    """Call ``step`` at ``rate_hz`` until ``stop`` is set or ``seconds`` (> 0) have passed."""
    timer = CycleTimer(rate_hz)
    end = time.monotonic() + seconds if seconds > 0 else math.inf
    while not stop.is_set() and time.monotonic() < end:
        step()
        timer.wait()


@contextmanager
def pty_device() -> Iterator[tuple[int, str]]:
    """Open a pseudo-terminal pair; yield the controller fd and the device path (also printed on
    stdout for the host). The device side is raw and stays open while the emulator runs, so hosts
    can open, close and re-open it."""
    import tty

    controller, device = os.openpty()
    try:
        tty.setraw(device)
        path = os.ttyname(device)
        print(path, flush=True)
        yield controller, path
    finally:
        os.close(controller)
        os.close(device)
