"""The mapping config keys the teleop helpers and the robots' mapping strategies read.

``telesurg.services.mapping.MappingConfig`` has them all; a strategy sees its pair's config as a
:class:`MappingSettings` (units in the names: mm, Hz, rad, deg).
"""

from __future__ import annotations

from typing import Any, Protocol


class MappingSettings(Protocol):
    """The mapping config as the teleop helpers and the mapping strategies see it."""

    service: str  # the mapping service's instance id
    mode: str  # the mapping mode
    model: str  # the slave robot
    robot: dict[str, Any]  # the robot's own knobs (RobotSpec.make_config)
    scale: float  # the operator's initial motion scale
    orientation: str  # follow | fixed
    keep_tilt: bool  # position mode: keep the instrument's tilt from the vertical
    master_mode: str  # pen | virtual_trocar
    virtual_trocar_mm: tuple[float, float, float]
    dummy_forceps_mm: float
    master_to_slave_rpy_deg: tuple[float, float, float]
    master_frame: str  # fixed | work
    work_frame_rpy_deg: tuple[float, float, float]
    camera: str  # camera id ("" = none)
    master_timeout_ms: float
    slave_timeout_ms: float
    max_joint_step_rad: float
    target_hz: float  # setpoint_cp rate
    workspace_min_mm: tuple[float, float, float]
    workspace_max_mm: tuple[float, float, float]
    latency_log: str  # .npy path of the latency trace ("" = none)
    slave_source: str  # the only sender of the slave's streams taken
    slave_passivity: bool  # TDPA's slave passivity controller on the targets
    haptics_force_scale: float  # master force per slave contact force (the master's setting)
    limit_wall_margin_deg: float  # the joint-limit wall's distance before the limit
