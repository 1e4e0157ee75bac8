"""Safe flight: what a robot may fly, how robots keep apart, and what counts as a collision.

Both sides implement these rules: the JAX environment (`jaxmripp.sim.flight`, applied by
`jaxmripp.sim.env` for every planner alike) and the onboard runtime
(`jaxmripp.runtime.flight`, applied by its safety filter whatever scores the candidates).

Obstacles (`safety.flight`)
    known_free   a candidate is offered only if every voxel its line of flight traverses
                 (`jaxmripp.spec.grid`) is FREE in the robot's own map. Maps copy codes from
                 the truth, so such a flight never enters a building. A robot's own voxel is
                 FREE in its map (it is there).
    truncate     candidates avoid voxels mapped OCCUPIED only; the robot flies the known-free
                 part of the segment and stops midway through the last piece before the
                 first voxel its map does not know to be FREE (a `blocked` move, charged as
                 flown). Intents announce the part that will be flown.
    optimistic   the unsafe reference: unknown voxels count as free. Only for measuring what
                 safety costs; flights are checked against the truth and stop before a
                 building, which counts an obstacle collision.

Closest approach of two flights
    Robots fly their segments at one common speed, starting together: robot A at a0 -> a1
    is at a0 + u_A min(t, |a1 - a0|) at time t (u_A its unit direction; a hovering robot
    has a zero-length segment). The closest approach of A and B is the minimum of their
    distance over t >= 0: a clamped quadratic on [0, min(L_A, L_B)] and on
    [min(L_A, L_B), max(L_A, L_B)], where the shorter flight hovers at its end.

Robots in radio range
    A candidate is offered only if its flight's closest approach to every robot heard this
    round, hovering where it was heard, exceeds d_c. With `safety.escape`, a flight that
    takes the robot no closer to a robot heard (`takes_no_closer`: turning in place, or
    flying away from it) is clear of that robot whatever their distance: two robots that
    came within d_c while out of radio range then part, instead of both being left with
    nothing on offer (and retired) for the rest of the episode. Robots then choose at once and announce
    the chosen segment (the intent) to the robots in range; the lower id goes first. A
    robot whose chosen flight comes within d_c (closest approach <= d_c) of the announced
    flight of a lower-id robot in range *holds*: it stays where it is
    this step, is charged nothing, and chooses again next step. One round suffices: the
    lower-id robot either flies what it announced or holds itself, and its flight was
    kept clear of the holding robot's position by the candidate rule above.

Collisions (the environment's ground truth)
    obstacle: a flight that enters a voxel occupied in the truth; it stops before it.
    robot: a pair of robots, at least one of them flying, whose actual flights come closer
    than d_c (closest approach < d_c) from at least d_c apart -- counted once per pair and
    step, as `in range` when the two were in radio range when they decided and `out of
    range` otherwise. A pair already closer than d_c was counted when it came so close;
    parting (`safety.escape`) is no new collision.
    Robots start on take-off pads `robots.pad_spacing` apart (more than d_c) in the world's
    y = start_y face: robot i at start + spacing (i mod m, 0, i div m), m = ceil(sqrt(N)).
"""

from jaxmripp.spec.vectors import components, dot, rounded, unit

FLIGHT_MODES = ("known_free", "truncate", "optimistic")


def closest_approach(a0, a1, b0, b1, xp):
    """(..., 3) x 4, broadcasting -> (...,): the least distance between robots flying
    a0 -> a1 and b0 -> b1 at one common speed from the same moment (above). Float32 in,
    float32 out; `xp` is numpy or jax.numpy, and both give the same bits
    (`jaxmripp.spec.vectors`)."""
    a0, a1, b0, b1 = (components(v) for v in (a0, a1, b0, b1))
    da = [e - s for s, e in zip(a0, a1)]
    db = [e - s for s, e in zip(b0, b1)]
    la, lb = xp.sqrt(dot(da, da, xp)), xp.sqrt(dot(db, db, xp))
    ua, ub = unit(da, la, xp), unit(db, lb, xp)
    short, long = xp.minimum(la, lb), xp.maximum(la, lb)
    # Phase 1, t in [0, short]: both fly. Phase 2, t in [short, long]: the longer flight
    # goes on while the other hovers at its end; the gap there is r(short) + w2 (t - short).
    r0 = [a - b for a, b in zip(a0, b0)]
    w1 = [u - v for u, v in zip(ua, ub)]
    w2 = [xp.where(la > lb, u, -v) for u, v in zip(ua, ub)]
    gap1 = _least_gap(r0, w1, short, xp)
    gap2 = _least_gap(_along(r0, w1, short, xp), w2, long - short, xp)
    return xp.minimum(gap1, gap2)


def _along(r, w, t, xp) -> list:
    """r + w t, on component triples."""
    return [a + rounded(b * t, xp) for a, b in zip(r, w)]


def _least_gap(r0, w, hi, xp):
    """min over t in [0, hi] of |r0 + w t|, on component triples."""
    ww = dot(w, w, xp)
    t = xp.clip(-dot(r0, w, xp) / xp.where(ww > 0, ww, 1.0), 0.0, hi)
    gap = _along(r0, w, t, xp)
    return xp.sqrt(dot(gap, gap, xp))


def takes_no_closer(start, end, other):
    """Flights start -> end (..., 3) and robots hovering at `other` (..., 3) -> (...,) bool:
    the flight never brings the robot closer to the other one than it is at the start,
    (start - other) . (end - start) >= 0, summed in x, y, z order. Plain arithmetic, so
    NumPy and JAX arrays share it."""
    away = (start - other) * (end - start)
    return away[..., 0] + away[..., 1] + away[..., 2] >= 0
