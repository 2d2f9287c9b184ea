"""The camera image message: its own size limits on its own key, the bin field's rules."""

from __future__ import annotations

import msgpack
import pytest
from telesurg.shared.errors import MessageError
from telesurg.shared.keys import Keys
from telesurg.shared.messages import (
    MAX_IMAGE_BYTES,
    MAX_IMAGE_PAYLOAD_BYTES,
    MAX_PAYLOAD_BYTES,
    CameraImage,
    Header,
    JointState,
    decode,
    decode_as,
)

H = Header("camera", 3, 1_700_000_000_000_000_000)


def _image(data: bytes) -> CameraImage:
    return CameraImage(
        H, "endo", 5, 320, 240, "jpeg", "mono", 0.0, 290.0, 290.0, 160.0, 120.0, 1.0, 0.2, 0, data
    )


def test_a_large_frame_decodes_only_as_an_image() -> None:
    msg = _image(b"\xff" * 200_000)  # a 640x480 JPEG is ~43 kB; this is well above the 64 KiB limit
    payload = msg.encode()
    assert len(payload) > MAX_PAYLOAD_BYTES
    assert decode_as(payload, CameraImage) == msg
    with pytest.raises(MessageError, match="limit 65536"):
        decode(payload)  # the generic decoder keeps the small limit


def test_a_small_frame_is_still_refused_by_the_generic_decoder() -> None:
    with pytest.raises(MessageError, match="not a valid MessagePack payload"):
        decode(_image(b"\xff\xd8").encode())  # no bin values outside the image key


def test_image_limits() -> None:
    with pytest.raises(MessageError, match="bytes, limit"):
        decode_as(b"\x00" * (MAX_IMAGE_PAYLOAD_BYTES + 1), CameraImage)
    d = msgpack.unpackb(_image(b"x").encode())
    d["data"] = b""
    with pytest.raises(MessageError, match="must not be empty"):
        decode_as(msgpack.packb(d, use_bin_type=True), CameraImage)
    d["data"] = "text, not bin"
    with pytest.raises(MessageError, match="must be bytes"):
        decode_as(msgpack.packb(d, use_bin_type=True), CameraImage)
    d["data"] = b"x"
    d["width"] = 0
    with pytest.raises(MessageError, match="width"):
        decode_as(msgpack.packb(d, use_bin_type=True), CameraImage)
    assert MAX_IMAGE_BYTES < MAX_IMAGE_PAYLOAD_BYTES


def test_another_type_on_the_image_key_is_refused() -> None:
    js = JointState(H, ("j1",), (0.0,)).encode()
    with pytest.raises(MessageError, match="expected 'camera_image'"):
        decode_as(js, CameraImage)


def test_camera_keys() -> None:
    k = Keys("lab")
    assert k.camera("endo", "image") == "telesurg/lab/camera/endo/image"
    assert k.camera("endo", "measured_cp") == "telesurg/lab/camera/endo/measured_cp"
    assert k.safety("arm1", "video") == "telesurg/lab/safety/arm1/video"
    with pytest.raises(ValueError):
        k.camera("endo", "nope")
