"""Safe flight between robots, in NumPy: the rules of `jaxmripp.spec.flight`.

The candidate rule against the robots heard this round and the intent (hold) rule. The JAX implementation is `jaxmripp.sim.flight`; both take the closest
approach of two flights from the specification itself (one function for NumPy and JAX).
"""

from __future__ import annotations

import numpy as np

from jaxmripp.spec import flight as spec

F32 = np.float32


def closest_approach(a0, a1, b0, b1) -> np.ndarray:
    """(..., 3) x 4, broadcasting -> (...,) float32 `jaxmripp.spec.flight.closest_approach`
    (a hovering robot has a zero-length flight)."""
    return spec.closest_approach(*(np.asarray(x, F32) for x in (a0, a1, b0, b1)), np)


def clear_of_robots(start, ends, others, collision_distance, escape: bool = False
                    ) -> np.ndarray:
    """Starts (3,) or (M, 3), ends (M, 3), (R, 3) robots heard -> (M,) True where the
    flight start -> end keeps more than d_c from every robot heard, each hovering where it
    was heard; with `escape` also where it takes the robot no closer to it."""
    ends = np.asarray(ends, F32).reshape(-1, 3)
    others = np.asarray(others, F32).reshape(-1, 3)
    if len(others) == 0:
        return np.ones(len(ends), bool)
    a0, a1, b = np.asarray(start, F32).reshape(-1, 1, 3), ends[:, None, :], others[None]
    clear = closest_approach(a0, a1, b, b) > F32(collision_distance)  # (M, R)
    if escape:
        clear |= spec.takes_no_closer(a0, a1, b)
    return np.all(clear, axis=-1)


def yields_to(own_id: int, start, target, intents, collision_distance
              ) -> tuple[int, float] | None:
    """The hold rule for one robot flying start -> target: the lowest-id robot below
    `own_id` whose announced flight comes within d_c of it, with that closest approach,
    or None. intents: {sender: (position, target or None)} of the robots heard; a None
    target (hovering) announces no flight."""
    conflicts = []
    for sender, (position, intent) in intents.items():
        if intent is None or sender >= own_id:
            continue
        gap = float(closest_approach(start, target, position, intent))
        if gap <= F32(collision_distance):
            conflicts.append((sender, gap))
    return min(conflicts) if conflicts else None
