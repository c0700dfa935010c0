"""Small spec helpers shared by the transforms."""

from __future__ import annotations


def action_range(env) -> float:
    """Width ``high - low`` of the bounds of ``env``'s ``"action"`` (first element), in m/s^2.

    Transforms that normalise by the action range (``InterventionCost``, ``JerkPenalty``) read it
    from their parent env the first time it is needed.
    """
    spec = env.full_action_spec["action"]
    return float((spec.space.high - spec.space.low).flatten()[0])
