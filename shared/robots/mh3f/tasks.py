"""The MH3F's training tasks on its scene's tissue (``scene.xml``; ``shared/tasks.py``).

* ``mh3f-targets`` — a Fitts-style reciprocal pointing task: touch the tissue at the scene's two
  targets (``target_a``, ``target_b``: 57 mm apart) in turn, four touches, each held 0.3 s within
  5 mm (index of difficulty log2(D/W + 1) = 2.8 bits with W the 10 mm target).
* ``mh3f-wire`` — a ring along a wire: follow an S-shaped wire 15 mm above the tissue (a sine of
  25 mm amplitude over 80 mm) from end to end without the tip leaving the 5 mm tube around it.

Both start with the tip at the site's home pose (the forceps 40 mm above the tissue), in the
arm's default (non-trocar) control mode: in this scene the tissue lies beyond the trocar's reach.

* ``mh3f-trocar-targets`` — the pointing task through the trocar, in trocar mode: two targets
  31 mm apart on the organ of ``scene_trocar_task.xml`` under the trocar. The harness first runs
  the insert flow (posture adjustment by PTP from ``TROCAR_Q_START``, insert to trocar mode,
  master–slave), as the surgeon's assistant would set the arm up (docs/study.md).

The RCM error is scored whenever the arm is in trocar mode.
"""

from __future__ import annotations

import math

from telesurg.shared.tasks import Goal, TaskSpec, Vec3, register

HOME_TIP = (0.835, 0.0, 0.301)  # m: the forceps tip at the site's home pose (README, "Tissue")
TISSUE_CENTRE = (0.835, 0.0, 0.235)  # m: the tissue body (scene.xml)
TISSUE_SEMI_AXES = (0.09, 0.08, 0.025)  # m: its ellipsoid
TOUCH_DEPTH_M = 0.0005  # a touch presses the tissue this deep (0.2 N at its 0.4 N/mm)


def tissue_top(
    x: float, y: float, centre: Vec3 = TISSUE_CENTRE, semi_axes: Vec3 = TISSUE_SEMI_AXES, what: str = "tissue"
) -> float:
    """z (m) of the upper surface above (x, y) of a tissue ellipsoid (undeformed): the scene's
    tissue, or ``centre`` / ``semi_axes`` (m) of another (the organ of scene_trocar_task.xml)."""
    (cx, cy, cz), (a, b, c) = centre, semi_axes
    r = 1.0 - ((x - cx) / a) ** 2 - ((y - cy) / b) ** 2
    if r < 0:
        raise ValueError(f"({x}, {y}) is not above the {what}")
    return cz + c * math.sqrt(r)


def touch(x: float, y: float, radius_m: float = 0.005, dwell_s: float = 0.3) -> Goal:
    """A target on the tissue at (x, y): the tip touching its surface."""
    return Goal((x, y, tissue_top(x, y) - TOUCH_DEPTH_M), radius_m, dwell_s)


A, B = (0.815, -0.02), (0.855, 0.02)  # the scene's target_a, target_b (x, y)

TARGETS = TaskSpec(
    name="mh3f-targets",
    robot="mh3f",
    kind="targets",
    instructions="Touch the green target, then the blue one, in turn: hold each touch until it is taken.",
    goals=(touch(*A), touch(*B), touch(*A), touch(*B)),
    start_tip=HOME_TIP,
    force_limit_n=2.0,
    time_limit_s=60.0,
)

WIRE_Z = 0.275  # m: the wire's height, 15 mm above the tissue's top
WIRE = tuple(
    (0.795 + 0.08 * u, 0.025 * math.sin(2 * math.pi * u), WIRE_Z) for u in (i / 32 for i in range(33))
)

PATH = TaskSpec(
    name="mh3f-wire",
    robot="mh3f",
    kind="path",
    instructions="Bring the ring onto the wire at its near end, slide it to the far end; do not touch it.",
    goals=(Goal(WIRE[-1], 0.005),),
    path=WIRE,
    tube_radius_m=0.005,
    start_tip=HOME_TIP,
    force_limit_n=2.0,
    time_limit_s=60.0,
)

# -- through the trocar: the organ of scene_trocar_task.xml, under the trocar at (0.5, 0, 0.2)

ORGAN_CENTRE = (0.57, 0.0, 0.132)  # m: the organ body (scene_trocar_task.xml)
ORGAN_SEMI_AXES = (0.045, 0.045, 0.015)  # m: its ellipsoid
#: rad: the start pose, above the trocar (the Jinno experiment's start_a, tools/experiment/jinno.py);
#: the insert flow from there leaves the tip at TROCAR_START_TIP, 50 mm beyond the trocar
TROCAR_Q_START = (0.0, -0.2, 0.6, -0.8, -1.0, 0.0)
TROCAR_START_TIP = (0.529, 0.0, 0.159)


def organ_touch(x: float, y: float, radius_m: float = 0.005, dwell_s: float = 0.3) -> Goal:
    """A target on the organ's surface at (x, y)."""
    top = tissue_top(x, y, ORGAN_CENTRE, ORGAN_SEMI_AXES, "organ")
    return Goal((x, y, top - TOUCH_DEPTH_M), radius_m, dwell_s)


# the scene's organ_target_a, organ_target_b (x, y): 31 mm apart. Through the trocar the wrist moves
# about five times as far as the tip (the forceps is 500 mm, the tip ~90 mm in): a 31 mm reach
# swings J1 by ~40°, so the targets are closer than on the open tissue
TA, TB = (0.560, -0.012), (0.580, 0.012)

TROCAR_TARGETS = TaskSpec(
    name="mh3f-trocar-targets",
    robot="mh3f",
    kind="targets",
    instructions=(
        "Through the trocar: touch the green target on the organ, then the blue one, in turn; "
        "hold each touch until it is taken."
    ),
    goals=(organ_touch(*TA), organ_touch(*TB), organ_touch(*TA), organ_touch(*TB)),
    start_tip=TROCAR_START_TIP,
    force_limit_n=2.0,
    rcm_limit_mm=2.0,
    time_limit_s=60.0,
    scene="scene_trocar_task.xml",
    setup="trocar",
    q_start=TROCAR_Q_START,
)

register(TARGETS)
register(PATH)
register(TROCAR_TARGETS)
