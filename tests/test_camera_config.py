"""The camera's config checks, and what the launcher asks before it starts a site with a camera."""

from __future__ import annotations

import pytest
from telesurg.services.camera import CameraConfig, unavailable
from telesurg.shared.errors import ConfigError


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"source": "webcam"}, "source 'webcam' invalid; valid: sim, video"),
        ({"source": "video"}, "needs url"),
        ({"fps": 0.0}, "fps"),
        ({"quality": 101}, "quality"),
        ({"width": 8}, "width"),
    ],
)
def test_bad_settings_are_refused_by_name(changes: dict[str, object], match: str) -> None:
    cfg = CameraConfig(**changes)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=match):
        cfg.validate()


@pytest.mark.parametrize("model", ["mh3f", "plas", "vip"])
def test_every_builtin_scene_has_an_endoscope(model: str) -> None:
    assert unavailable(CameraConfig(model=model)) == ""


def test_a_scene_without_the_camera_or_an_unknown_robot_turns_the_camera_off() -> None:
    assert "has no camera 'nope'" in unavailable(CameraConfig(scene_camera="nope"))
    assert "unknown" in unavailable(CameraConfig(model="no_such_robot"))
    assert unavailable(CameraConfig(source="video", url="clip.mp4")) == ""  # no GL needed
