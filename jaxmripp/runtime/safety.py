"""The onboard safety filter, and why a robot hovers when it leaves nothing.

Whatever proposes the candidates (the robot's own sampler or a caller) and whatever
scores them (policy or greedy rule), a pose is only flown if this filter passes it: inside
the world, a straight flight that is known free (every voxel it traverses, by the rule of
`jaxmripp.spec.grid`, is FREE in the robot's map), a flight whose closest approach to every
robot heard this round (hovering where it was heard) exceeds d_c, and affordable
(`jaxmripp.spec.flight`). The sampler applies the same rules; the filter repeats them
because supplied candidates were not checked at all. The intent (hold) rule comes after
the decision, in `OnboardPlanner.resolve`.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.runtime import candidates as cands
from jaxmripp.runtime import flight
from jaxmripp.runtime.mapping import OccupancyMap, inside_world
from jaxmripp.runtime.weights import RuntimeSpec

RULES = ("outside", "blocked", "crowded", "over_budget")


def check(c: cands.Candidates, position: np.ndarray, budget_left, occupancy: OccupancyMap,
          others: np.ndarray, spec: RuntimeSpec) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(L,) bool safe, and for each of RULES the (L,) bool candidates it rejects."""
    finite = np.all(np.isfinite(c.position), axis=-1)
    # Non-finite targets are judged "outside" and tested as the current position, so
    # that the traversal and distance tests below see only finite numbers.
    target = np.where(finite[:, None], c.position, position)
    outside = ~inside_world(target) | ~finite
    # Candidates share positions four by four: test each distinct flight once, and only
    # flights ending inside the world (the others are refused as outside anyway, and a
    # far-off target would need a huge traversal).
    unique, inverse = np.unique(target, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    judged = inside_world(unique)
    free, apart = np.ones(len(unique), bool), np.ones(len(unique), bool)
    free[judged] = occupancy.known_free(position, unique[judged], spec.shell[1])
    apart[judged] = flight.clear_of_robots(position, unique[judged], others,
                                           spec.collision_distance, spec.escape)
    why = {
        "outside": outside,
        "blocked": ~free[inverse],
        "crowded": ~apart[inverse],
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
                ("outside", "outside the world"),
                ("blocked", "through voxels not known free"),
                ("crowded", "passing within d_c of a robot heard"),
                ("over_budget", "over budget"))
                if stats[k])
            return f"hover: no candidate left of {stats['draws']} draws ({counts})"
        return "hover: none of the supplied candidates is offered as valid"
    counts = ", ".join(f"{int((why[k] & offered).sum())} {text}" for k, text in (
        ("blocked", "cross a voxel not known free"),
        ("crowded", f"pass within d_c = {spec.collision_distance:g} of a robot heard"),
        ("over_budget", f"over the budget left ({budget:.4g})"),
        ("outside", "outside the world")) if (why[k] & offered).any())
    return f"hover: the safety filter rejected all {int(offered.sum())} candidates ({counts})"
