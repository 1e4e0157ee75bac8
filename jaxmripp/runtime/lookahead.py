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
from jaxmripp.runtime.mapping import OccupancyMap
from jaxmripp.runtime.weights import RuntimeSpec
from jaxmripp.spec import layout

F32 = np.float32
_UNKNOWN = layout.FEATURES.index("view_unknown")
_FACADE = layout.FEATURES.index("view_facade")
_WINDOWS = layout.features(belief=True).index("view_windows")


def draw_shape(spec: RuntimeSpec) -> tuple[int, int, int]:
    """The uniforms one robot's lookahead input takes: one candidate draw per followed
    candidate."""
    return (spec.ahead_branches, spec.positions * spec.oversample - 1, 3)


def ahead_rates(uniforms: np.ndarray, features: np.ndarray, mask: np.ndarray,
                c: cands.Candidates, budget_left, occupancy: OccupancyMap,
                others: np.ndarray, spec: RuntimeSpec,
                rates: np.ndarray | None = None) -> np.ndarray:
    """(L,) float32 `ahead_rate` for candidates `c` with `spec.features` columns `features`
    (L, F, the lookahead input not yet among them), feasibility `mask` (L,), on the
    robot's map with the robots heard this round at `others` (M, 3); `uniforms` has
    `draw_shape(spec)`. With `spec.ahead_rated` the facade is weighed by the robot's
    facade rates `rates` (G, G) int (`jaxmripp.runtime.belief.facade_rates`), those its
    `view_windows` column was computed with. The followed candidates are searched
    together, each on its own copy of the map."""
    weight, discount = F32(spec.ahead_facade_weight), F32(spec.ahead_discount)
    shell = spec.shell[1]
    if spec.ahead_rated and rates is None:
        raise ValueError("ahead_rates: the lookahead input is rated (ahead_rated); pass the "
                         "robot's facade rates")
    facade_column = _WINDOWS if spec.ahead_rated else _FACADE
    facade_rates = rates if spec.ahead_rated else None
    gain = layout.view_value(features[:, _UNKNOWN], features[:, facade_column], weight)
    rate = view.per_cost(gain, c.cost, shell)
    ranked = np.where(mask, rate, -np.inf).astype(F32)
    followed = np.argsort(-ranked, kind="stable")[:spec.ahead_branches]
    # The j-th best candidate takes the j-th block of draws; an infeasible one is skipped.
    draws = np.asarray(uniforms, F32).reshape(draw_shape(spec))[:len(followed)]
    feasible = np.isfinite(ranked[followed])
    first, draws = followed[feasible], draws[feasible]
    values = rate.copy()
    if not len(first):
        return values.astype(F32)
    after = view.after_views(occupancy.codes, occupancy.top, c.position[first],
                             c.heading[first], spec.gain, occupancy.size)
    following = cands.sample_many(draws, c.position[first], c.heading[first],
                                  F32(budget_left) - c.cost[first], after, occupancy.size,
                                  others, spec)
    # Only feasible second flights can be taken: only they are looked at (in the padded
    # copies, as the draws were).
    valid = following.valid
    unknown, facade = np.zeros(valid.shape, F32), np.zeros(valid.shape, F32)
    gains = view.view_gain(after, occupancy.top, following.position[valid],
                           following.heading[valid], spec.gain, occupancy.size,
                           rows=np.nonzero(valid)[0], rates=facade_rates)
    unknown[valid], facade[valid] = gains[0], gains[-1]
    rates = view.per_cost(gain[first, None] + discount * layout.view_value(unknown, facade,
                                                                          weight),
                          c.cost[first, None] + discount * following.cost, shell)
    best = np.max(np.where(valid, rates, -np.inf), axis=-1)
    values[first] = np.where(valid.any(axis=-1), np.maximum(rate[first], best),
                             rate[first])
    return values.astype(F32)
