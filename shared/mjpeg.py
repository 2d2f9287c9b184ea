"""The MJPEG stream a browser shows in an ``<img>`` (``multipart/x-mixed-replace``).

A browser finishes a part, and shows it, once it has read the *next* part's headers (Chromium's
multipart parser completes a part there, not at the boundary). A stream that sends each part's
headers with its own frame shows every frame one frame period late; this one sends them right
after the frame before, so a frame is shown as soon as it has arrived.
"""

from __future__ import annotations

CONTENT_TYPE = "multipart/x-mixed-replace; boundary=frame"
#: the stream's first bytes: the first boundary and the first part's headers
START = b"--frame\r\nContent-Type: image/jpeg\r\n\r\n"


def part(jpeg: bytes) -> bytes:
    """One frame, then the next boundary and the next part's headers."""
    return jpeg + b"\r\n" + START
