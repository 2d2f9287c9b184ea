"""The operator's motion scale commands, shared by every mapping mode.

``scale_up`` / ``scale_down`` step through :data:`SCALE_STEPS` from the step nearest the current
scale; ``set_scale value=V`` takes any V in (0, 2]. Anything else is refused with the reason, and
the scale is left as it was.

**While following** (the clutch pressed, the slave following), the mapping re-anchors at the
current target so a new scale makes no jump, and the step is bounded: the scale may rise at most
to the next step of :data:`SCALE_STEPS` above the current scale (``scale_up`` always fits;
``set_scale 2.0`` from 0.5 is refused: release the clutch first); lowering it is always allowed.
Every answer given while following says so (:data:`WHILE_FOLLOWING`): a refusal "… refused while
following …", an accepted change "scale 0.5 → 0.7 while following (re-anchored)".
"""

from __future__ import annotations

#: the operator's scale steps (scale_up / scale_down)
SCALE_STEPS = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0, 1.5, 2.0)
#: the largest scale an operator may set
MAX_SCALE = 2.0
SCALE_COMMANDS = ("scale_up", "scale_down", "set_scale")
#: the words of every scale answer given while the pair follows (so a reader of the answer knows
#: which rule applied without asking the teleop state, which may have changed since)
WHILE_FOLLOWING = "while following"


def new_scale(name: str, args: dict[str, str], current: float) -> tuple[float | None, str]:
    """The scale a scale command asks for, or ``None`` and the refusal's reason.

    Args:
        name: ``scale_up``, ``scale_down`` or ``set_scale``.
        args: the command's arguments (``value`` for ``set_scale``).
        current: the scale in use.
    """
    if name == "set_scale":
        try:
            new = float(args.get("value", "nan"))
        except ValueError:
            new = float("nan")
    elif name in ("scale_up", "scale_down"):
        i = min(range(len(SCALE_STEPS)), key=lambda j: abs(SCALE_STEPS[j] - current))
        i = min(i + 1, len(SCALE_STEPS) - 1) if name == "scale_up" else max(i - 1, 0)
        new = SCALE_STEPS[i]
    else:
        return None, f"{name!r} is not a scale command; valid: {', '.join(SCALE_COMMANDS)}"
    if not 0.0 < new <= MAX_SCALE:
        return None, f"{name} refused: scale must be in (0, {MAX_SCALE:g}], got {new}"
    return new, ""


def follow_step_problem(current: float, new: float) -> str:
    """Why changing the scale from ``current`` to ``new`` while following is refused ("" = fine):
    a rise beyond the next step of :data:`SCALE_STEPS` above ``current``."""
    if new <= current:
        return ""
    bound = next((s for s in SCALE_STEPS if s > current + 1e-9), MAX_SCALE)
    if new <= bound + 1e-9:
        return ""
    return (
        f"scale {current:.3g} → {new:.3g} refused {WHILE_FOLLOWING}: at most one step up "
        f"(to {bound:.3g}); release the clutch for a larger change"
    )
