"""The VIP's training task on ``scene_pegs.xml`` (``shared/tasks.py``).

* ``vip-pegs`` — an FLS-like peg transfer between the two arms: arm1 grasps the peg standing on
  the start pad (its jaws 2 mm below the peg's top), lifts it 20 mm to the hand-over point, arm2
  takes it lower down (4 mm above its bottom) coming in from its side, arm1 lets go, arm2 places
  it on the target pad and opens.

The arms start at the poses from which the scene's grasps are made (README, "The pegs scene"):
arm1 above the peg, its instrument 5° off vertical; arm2 25 mm back along its instrument from its
grasp at the hand-over, 62° off vertical. Each arm's VIP is set 500 mm along its instrument from
these poses (``[mapping.robot] vips_mm``): the instruments keep their tilts as the wrists move, so
a held peg stays upright (with the paper's VIP, 110 mm from the wrist, arm2's carry tilted it
past the 22° at which it falls over when let go).
"""

from __future__ import annotations

from telesurg.shared.tasks import Goal, TaskSpec, register

PEG_HALF_HEIGHT = 0.0075  # m: the peg is a 6 mm x 15 mm cylinder
PAD_TOP = -0.205  # m: the peg board's pads (scene_pegs.xml)
START = (-0.035, -0.035, PAD_TOP + PEG_HALF_HEIGHT)  # m: the peg's centre on the start pad
HAND_OVER = (-0.025, -0.015, PAD_TOP + PEG_HALF_HEIGHT + 0.020)  # m: lifted 20 mm on the way
TARGET = (-0.015, 0.005, PAD_TOP + PEG_HALF_HEIGHT)  # m: its centre on the target pad
Q_ARM1 = (0.3426, 0.7962, -0.1030, 1.2215, 0.3029)  # rad/m: arm1 above the peg
Q_ARM2 = (0.3658, 0.7597, -0.1454, 1.2379, 1.4551)  # arm2 25 mm back from its hand-over grasp
VIPS_MM = {"arm1": [-0.6, -6.5, 343.1], "arm2": [321.2, 275.8, 59.4]}  # 500 mm along each instrument

PEGS = TaskSpec(
    name="vip-pegs",
    robot="vip",
    kind="transfer",
    instructions=(
        "Left hand: pick up the peg and lift it. Right hand: take it from below, then the left lets "
        "go. Place it on the green pad and open."
    ),
    goals=(Goal(START, 0.005), Goal(HAND_OVER, 0.008), Goal(TARGET, 0.005)),
    start_tip=(-0.0342, -0.0343, -0.155),  # m: arm1's wrist at Q_ARM1
    start_tips=((-0.0342, -0.0343, -0.155), (0.0, 0.006, -0.1636)),
    time_limit_s=45.0,
    scene="scene_pegs.xml",
    q_start=Q_ARM1 + Q_ARM2,
    arms=("arm1", "arm2"),
    obj="peg",
    grasp_offset=(0.0, 0.0, -0.012),  # the jaw centre, 12 mm beyond the wrist W
    obj_grasps=((0.0, 0.0, PEG_HALF_HEIGHT - 0.002), (0.0, 0.0, -PEG_HALF_HEIGHT + 0.004)),
    tool_axis=(0.0, 0.0, -1.0),
    mapping_set=tuple(f"robot.vips_mm.{arm}={v}" for arm, v in VIPS_MM.items()),
)
register(PEGS)
