"""The small helpers several services share: arm pairs, the joint-step limit, the master→slave
rotation from roll/pitch/yaw, the web viewer's address, and the free-port check of the servers."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import held_port
from telesurg.services.common import check_port_free
from telesurg.shared.errors import ConfigError
from telesurg.shared.kinematics.transforms import rot_x, rot_z, rpy_matrix
from telesurg.shared.limits import limit_step
from telesurg.shared.pairs import parse_pair
from telesurg.shared.viewer import viewer_url


def test_parse_pair_splits_and_checks_the_arm_ids() -> None:
    assert parse_pair("m1:arm1") == ("m1", "arm1")
    with pytest.raises(ConfigError, match="master_arm:slave_arm"):
        parse_pair("m1-arm1")
    with pytest.raises(ConfigError):
        parse_pair("m1:arm/1")  # not a valid arm id (it would split a key)
    with pytest.raises(ConfigError):
        parse_pair(":arm1")


def test_limit_step_scales_the_whole_step_and_keeps_its_direction() -> None:
    lim = np.array([0.1, 0.1, 0.2])
    small = np.array([0.05, -0.1, 0.2])
    assert limit_step(small, lim) is small  # within the limits: unchanged
    out = limit_step(np.array([0.4, -0.1, 0.2]), lim)
    np.testing.assert_allclose(out, [0.1, -0.025, 0.05])  # the 0.4 joint sets the ratio (4)
    assert np.all(np.abs(out) <= lim + 1e-15)


def test_rpy_matrix_is_yaw_pitch_roll_in_degrees() -> None:
    np.testing.assert_allclose(rpy_matrix((0.0, 0.0, 90.0)), rot_z(np.pi / 2), atol=1e-15)
    np.testing.assert_allclose(rpy_matrix((30.0, 0.0, 0.0)), rot_x(np.radians(30.0)), atol=1e-15)
    r = rpy_matrix((10.0, 20.0, 30.0))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    # roll applied first: the x axis is turned only by pitch and yaw
    np.testing.assert_allclose(r @ [1.0, 0.0, 0.0], rpy_matrix((0.0, 20.0, 30.0)) @ [1.0, 0.0, 0.0])


def test_viewer_url_quotes_the_grpc_address() -> None:
    url = viewer_url("rerun+http://127.0.0.1:9876/proxy", 9090)
    assert url == "http://localhost:9090/?url=rerun%2Bhttp://127.0.0.1:9876/proxy"


def test_check_port_free_names_what_a_taken_port_was_for() -> None:
    with (
        held_port() as port,
        pytest.raises(ConnectionError, match=f"grpc_port 127.0.0.1:{port} is not available: Address"),
    ):
        check_port_free("127.0.0.1", port, "grpc_port")
    check_port_free("127.0.0.1", port, "grpc_port")  # closed: free again (TIME_WAIT or not)
