"""The PLAS's training task on ``scene_pegs.xml`` (``shared/tasks.py``).

* ``plas-pegs`` — an FLS-like peg transfer between the two arms: arm1 grasps the peg standing on
  the blue start pad (its jaws 2 mm below the peg's top), lifts it 20 mm to the hand-over point,
  arm2 takes it lower down (4 mm above its bottom) coming in from the side, arm1 lets go, arm2
  carries it 65 mm to the green target pad, sets it down and opens.

The arms start at the poses from which the scene's grasps are made (README, "The pegs scene"):
arm1 25 mm above the peg, its forceps 40° off vertical; arm2 15 mm back along its forceps from
its grasp at the hand-over, 70° off vertical. A Cartesian master drives the PLAS through the
generic ``position`` mapping with ``keep_tilt``: each forceps keeps that tilt and turns only about
the vertical, so a held peg stays upright (with the orientation free, a carried peg tilts and
falls).
"""

from __future__ import annotations

from telesurg.shared.tasks import Goal, TaskSpec, register

PEG_HALF_HEIGHT = 0.0075  # m: the peg is a 6 mm x 15 mm cylinder
PAD_TOP = -0.205  # m: the peg board's surface (scene_pegs.xml)
START = (0.020, -0.050, PAD_TOP + PEG_HALF_HEIGHT)  # m: the peg's centre on the start pad
HAND_OVER = (0.020, -0.020, PAD_TOP + PEG_HALF_HEIGHT + 0.020)  # m: lifted 20 mm on the way
TARGET = (0.020, 0.045, PAD_TOP + PEG_HALF_HEIGHT)  # m: its centre on the target pad
Q_ARM1 = (0.0559, 0.6979, 0.7282, 0.6854, 0.0061, -1.3445)  # m/rad: arm1 above the peg
Q_ARM2 = (0.0741, 1.4541, 1.1813, -0.7877, -0.0113, -0.3744)  # arm2 15 mm back from its grasp

PEGS = TaskSpec(
    name="plas-pegs",
    robot="plas",
    kind="transfer",
    instructions=(
        "Left hand: pick up the peg and lift it. Right hand: take it from the side, then the left "
        "lets go. Place it on the green pad and open."
    ),
    goals=(Goal(START, 0.005), Goal(HAND_OVER, 0.008), Goal(TARGET, 0.005)),
    start_tip=(0.0228, -0.0505, -0.1705),  # m: arm1's tip at Q_ARM1
    start_tips=((0.0228, -0.0505, -0.1705), (0.0132, -0.0128, -0.1774)),
    time_limit_s=45.0,
    scene="scene_pegs.xml",
    q_start=Q_ARM1 + Q_ARM2,
    arms=("arm1", "arm2"),
    obj="peg",
    grasp_offset=(0.0, 0.0, -0.0045),  # the jaws' centre, 4.5 mm behind the tip (site armN_grasp)
    obj_grasps=((0.0, 0.0, PEG_HALF_HEIGHT - 0.002), (0.0, 0.0, -PEG_HALF_HEIGHT + 0.004)),
    tool_axis=(0.0, 0.0, 1.0),
    mapping="position",
    mapping_set=("keep_tilt=true",),
)
register(PEGS)
