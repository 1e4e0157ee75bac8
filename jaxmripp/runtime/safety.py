"""The onboard safety filter, and why a robot hovers when it leaves nothing.

Whatever proposes the candidates (the robot's own sampler or a caller) and whatever
scores them (policy or greedy rule), a pose is only flown if this filter passes it: inside
the world, a straight flight that enters no voxel the robot knows to be OCCUPIED, farther
than d_c from every robot heard this round, and affordable. The sampler applies the same
rules with the JAX env's half-voxel segment samples; the filter repeats them with an exact
voxel traversal (by default), because supplied candidates were not checked at all and the
sampled rule can step over the corner of an occupied voxel.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.runtime import candidates as cands
from jaxmripp.runtime.mapping import OccupancyMap, inside_world
from jaxmripp.runtime.weights import RuntimeSpec

RULES = ("outside", "blocked", "crowded", "over_budget")


def check(c: cands.Candidates, position: np.ndarray, budget_left, occupancy: OccupancyMap,
          others: np.ndarray, spec: RuntimeSpec, segment_check: str
          ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(L,) bool safe, and for each of RULES the (L,) bool candidates it rejects."""
    finite = np.all(np.isfinite(c.position), axis=-1)
    # Non-finite targets are judged "outside" and tested as the current position, so
    # that the segment and distance tests below see only finite numbers.
    target = np.where(finite[:, None], c.position, position)
    outside = ~inside_world(target) | ~finite
    # Candidates share positions four by four: traverse each distinct segment once.
    unique, inverse = np.unique(target, axis=0, return_inverse=True)
    if segment_check == "exact":
        clear = occupancy.exact_clear(position, unique)
    else:
        clear = occupancy.sampled_clear(position, unique, spec.shell[1])
    why = {
        "outside": outside,
        "blocked": ~clear[inverse.reshape(-1)],
        "crowded": ~cands.clear_of_robots(target, others, spec.collision_distance),
        "over_budget": ~(c.cost <= budget_left),  # NaN costs are over budget too
    }
    return ~np.any([why[rule] for rule in RULES], axis=0), why


def hover_reason(c: cands.Candidates, why: dict, stats: dict, budget_left,
                 spec: RuntimeSpec) -> str:
    """One line saying why no candidate is left: the budget, the sampler's draws, or the
    filter's rejections (counted per rule among the offered candidates)."""
    budget = float(budget_left)
    cheapest = min(spec.turn_cost, spec.shell[0])
    if budget < cheapest:
        return (f"hover: budget exhausted ({budget:.4g} left, the cheapest move costs "
                f"{cheapest:g})")
    offered = c.valid
    if not offered.any():
        if stats:  # the robot's own sampler kept nothing: say which rule took the draws
            counts = ", ".join(f"{stats[k]} {text}" for k, text in (
                ("outside", "outside the world"), ("blocked", "behind known obstacles"),
                ("crowded", "within d_c of a robot heard"), ("over_budget", "over budget"))
                if stats[k])
            return f"hover: no candidate left of {stats['draws']} draws ({counts})"
        return "hover: none of the supplied candidates is offered as valid"
    counts = ", ".join(f"{int((why[k] & offered).sum())} {text}" for k, text in (
        ("blocked", "cross a voxel known occupied"),
        ("crowded", f"within d_c = {spec.collision_distance:g} of a robot heard"),
        ("over_budget", f"over the budget left ({budget:.4g})"),
        ("outside", "outside the world")) if (why[k] & offered).any())
    return f"hover: the safety filter rejected all {int(offered.sum())} candidates ({counts})"
