"""Safe flight between robots, in NumPy: the rules of `jaxmripp.spec.flight`.

Closest approach of two flights flown at one common speed, the candidate rule against the
robots heard this round, and the intent (hold) rule with its priority. The JAX
implementation is `jaxmripp.sim.flight`; both compute in float32 with the same formulas.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.spec.flight import PRIORITIES, takes_no_closer

F32 = np.float32


def closest_approach(a0, a1, b0, b1) -> np.ndarray:
    """(..., 3) x 4 -> (...,) float32: the least distance between robots flying a0 -> a1
    and b0 -> b1 at one common speed from the same moment (the shorter flight hovers at
    its end; a hovering robot has a zero-length flight)."""
    a0, a1, b0, b1 = (np.asarray(x, F32) for x in (a0, a1, b0, b1))
    la = np.linalg.norm(a1 - a0, axis=-1, keepdims=True)
    lb = np.linalg.norm(b1 - b0, axis=-1, keepdims=True)
    ua = np.where(la > 0, (a1 - a0) / np.where(la > 0, la, F32(1)), F32(0))
    ub = np.where(lb > 0, (b1 - b0) / np.where(lb > 0, lb, F32(1)), F32(0))
    short, long = np.minimum(la, lb), np.maximum(la, lb)
    # Phase 1, t in [0, short]: both fly. Phase 2, t in [short, long]: the longer flight
    # goes on while the other hovers at its end; the gap there is r(short) + w2 (t - short).
    r0 = a0 - b0
    w1 = ua - ub
    w2 = np.where(la > lb, ua, -ub)
    gap1 = _least_gap(r0, w1, short)
    gap2 = _least_gap(r0 + w1 * short, w2, long - short)
    return np.minimum(gap1, gap2)


def _least_gap(r0, w, hi) -> np.ndarray:
    """min over t in [0, hi] of |r0 + w t|; shapes (..., 3), (..., 3), (..., 1)."""
    ww = np.sum(w * w, axis=-1, keepdims=True)
    t = np.clip(-np.sum(r0 * w, axis=-1, keepdims=True) / np.where(ww > 0, ww, F32(1)),
                F32(0), hi)
    return np.linalg.norm(r0 + w * t, axis=-1)


def clear_of_robots(start, ends, others, collision_distance, escape: bool = False
                    ) -> np.ndarray:
    """Starts (3,) or (M, 3), ends (M, 3), (R, 3) robots heard -> (M,) True where the
    flight start -> end keeps more than d_c from every robot heard, each hovering where it
    was heard; with `escape` also where it takes the robot no closer to it."""
    ends = np.asarray(ends, F32).reshape(-1, 3)
    others = np.asarray(others, F32).reshape(-1, 3)
    if len(others) == 0:
        return np.ones(len(ends), bool)
    m, n = len(ends), len(others)
    a0 = np.broadcast_to(np.asarray(start, F32).reshape(-1, 1, 3), (m, n, 3))
    a1 = np.broadcast_to(ends[:, None, :], (m, n, 3))
    b = np.broadcast_to(others[None], (m, n, 3))
    clear = closest_approach(a0, a1, b, b) > F32(collision_distance)
    if escape:
        clear |= takes_no_closer(a0, a1, b)
    return np.all(clear, axis=-1)


def goes_first(other_id: int, other_budget, own_id: int, own_budget, priority: str) -> bool:
    """True when robot `other_id` goes before robot `own_id` (`jaxmripp.spec.flight`):
    priority "id", the lower id; "budget", more budget left, then the lower id."""
    if priority not in PRIORITIES:
        raise ValueError(f"priority: got {priority!r}; allowed: {', '.join(PRIORITIES)}")
    lower_id = other_id < own_id
    if priority == "id":
        return lower_id
    other_budget, own_budget = F32(other_budget), F32(own_budget)
    return bool(other_budget > own_budget or (other_budget == own_budget and lower_id))


def yields_to(own_id: int, own_budget, start, target, intents, collision_distance,
              priority: str) -> tuple[int, float] | None:
    """The hold rule for one robot flying start -> target: the higher-priority robot
    (the first in priority order) whose announced flight comes within d_c of it, with that
    closest approach, or None. intents: {sender: (position, target or None, budget_left)}
    of the robots heard; a None target (hovering) announces no flight."""
    conflicts = []
    for sender, (position, intent, budget) in intents.items():
        if intent is None or not goes_first(sender, budget, own_id, own_budget, priority):
            continue
        gap = float(closest_approach(start, target, position, intent))
        if gap <= F32(collision_distance):
            order = (sender,) if priority == "id" else (-F32(budget), sender)
            conflicts.append((order, sender, gap))
    if not conflicts:
        return None
    _, sender, gap = min(conflicts)
    return sender, gap
