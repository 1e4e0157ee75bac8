"""The lookahead input (`ahead_rate` of `jaxmripp.spec.layout`) in NumPy, for one robot.

The rule is written once, in that module's docstring; `jaxmripp.sim.lookahead.ahead_rates`
is its JAX implementation. Both draw the candidates that follow a pose with the candidate
rule (`jaxmripp.runtime.candidates.sample` here), so given the same uniforms they follow the
same candidates and give the same values up to float32 rounding.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.runtime import candidates as cands
from jaxmripp.runtime import view
from jaxmripp.runtime.mapping import FREE, OccupancyMap
from jaxmripp.runtime.weights import RuntimeSpec
from jaxmripp.spec import layout

F32 = np.float32
_UNKNOWN = layout.FEATURES.index("view_unknown")
_FACADE = layout.FEATURES.index("view_facade")


def draw_shape(spec: RuntimeSpec) -> tuple[int, int, int]:
    """The uniforms one robot's lookahead input takes: one candidate draw per followed
    candidate."""
    return (spec.ahead_branches, spec.positions * spec.oversample - 1, 3)


def ahead_rates(uniforms: np.ndarray, features: np.ndarray, mask: np.ndarray,
                c: cands.Candidates, budget_left, occupancy: OccupancyMap,
                others: np.ndarray, spec: RuntimeSpec) -> np.ndarray:
    """(L,) float32 `ahead_rate` for candidates `c` with FEATURES columns `features`
    (L, F), feasibility `mask` (L,), on the robot's map with the robots heard this round at
    `others` (M, 3); `uniforms` has `draw_shape(spec)`."""
    weight, discount = F32(spec.ahead_facade_weight), F32(spec.ahead_discount)
    shell = spec.shell[1]
    gain = layout.view_value(features[:, _UNKNOWN], features[:, _FACADE], weight)
    rate = view.per_cost(gain, c.cost, shell)
    ranked = np.where(mask, rate, -np.inf).astype(F32)
    followed = np.argsort(-ranked, kind="stable")[:spec.ahead_branches]
    values = rate.copy()
    after = OccupancyMap(occupancy.size)
    after.top = occupancy.top
    for first, draws in zip(followed, np.asarray(uniforms, F32).reshape(draw_shape(spec))):
        if not np.isfinite(ranked[first]):
            continue  # an infeasible candidate is not followed
        heading = int(c.heading[first])
        after.codes = occupancy.codes.copy()
        after.codes[view.unknown_in_view(occupancy.codes, occupancy.top, c.position[first],
                                         heading, spec.fov_deg, spec.sensor_range,
                                         occupancy.size)] = FREE
        following = cands.sample(draws, c.position[first], heading,
                                 F32(budget_left) - c.cost[first], after, others, spec)
        unknown, facade = view.view_gain(after.codes, after.top, following.position,
                                         following.heading, spec.fov_deg, spec.sensor_range,
                                         occupancy.size)
        rates = view.per_cost(gain[first] + discount * layout.view_value(unknown, facade, weight),
                              c.cost[first] + discount * following.cost, shell)
        if following.valid.any():
            values[first] = max(rate[first], rates[following.valid].max())
    return values.astype(F32)
