"""The policy's input columns and how each is computed: written by the environment
(`jaxmripp.sim.observation.observe`), read by the policy, checked by the exporter and
rebuilt by the runtime (`jaxmripp.runtime.observation`). This docstring is the one
written rule; the two implementations must give the same float32 numbers for the same
state.

FEATURES, one row per candidate pose (position p, heading h, cost c) of a robot at
position q with budget b_left of its initial share b_0 (b = max(b_0, 1e-6) below):
    dx, dy, dz      (p - q) / shell[1], the offset over the largest candidate distance
    x, y, z         p, the absolute position in the unit cube
    heading_0..3    one-hot h (headings of `jaxmripp.spec.grid`)
    utility_mean    posterior mean of the robot's utility GP at the pose (p, angle of h)
    utility_std     square root of its posterior latent variance (clamped to [0, variance])
    comm_mean, comm_std  the same two for the communication GP
    cost            c = |p - q| + turn_cost [h != current heading]
    budget_after    (b_left - c) / b, the budget fraction left after the move
    view_unknown, view_facade, view_unknown_per_cost, view_facade_per_cost
                    the view gain of the pose on the robot's map (`jaxmripp.spec.view`)
    peer_distance   distance to the nearest robot heard, in shell lengths (`jaxmripp.spec.view`)
The GPs are read after this round's feeding (`jaxmripp.spec.feeding`; with the training
option gp.shared_utility the env's utility GP is the team's, a robot's is always its own).
ROBOT_STATE: q, one-hot current heading, b_left / b, step / T_max (T_max = episode length).
A centralised critic also reads every robot's ROBOT_STATE (robot-major) followed by the
N_GLOBAL_EXTRA team values: the discovered fraction and the mean budget left / b.
Padding candidates (invalid) still get rows computed by these formulas; the mask hides them.
Input groups can be ablated (`policy.comm_features`, `view_features`, `intent_features`):
the policy then multiplies the group's columns by 0 (`input_keep`), on both sides.

LOOKAHEAD INPUT (`policy.ahead_branches` n > 0): one more column after FEATURES,
`ahead_rate` (`features(ahead=True)`), the value `nbv_ahead` gives a candidate when it looks
two flights ahead (`jaxmripp.sim.lookahead`), with the discount d = `policy.ahead_discount`
and the facade weight w = `policy.ahead_facade_weight`. With g = view_value(view_unknown,
view_facade, w) and r = view.per_cost(g, cost) (`jaxmripp.spec.view`'s per_cost), the n
feasible candidates of largest r (ties: the lower index first) are followed, the k-th of
them with the k-th block of uniforms: for such a candidate a, its pose's unknown samples
(`jaxmripp.spec.view`: clear, inside the grid, mapped UNKNOWN) are set FREE in a copy of
the map, candidates b are drawn around a's pose by the candidate rule (budget: the robot's
budget left minus c(a); the robots heard this round), their g(b) are computed on that
copy, and
    ahead_rate(a) = max(r(a), max over feasible b of per_cost(g(a) + d g(b), c(a) + d c(b)));
every other row (not followed, or nothing feasible) holds r. With `policy.ahead_rated` (and
the belief input) the facade term of g is the belief-weighed one, view_windows for a (its
column) and for each b (on the copy, with the robot's facade rates that its view_windows
column was computed with): the value `nbv_targets` ranks by, its peers' claims aside. Rates that are equal in exact
arithmetic may differ in the last bit between the two sides (XLA may fuse g's multiply-add),
so such candidates may be followed in either order. The env draws robot i's k-th block
from `jax.random.split(key_i, n)[k]`, key_i = `jax.random.split(fold_in(step key, 1),
N)[i]`; the runtime from its own generator, after the candidates' draws.

BELIEF INPUT (`policy.belief_features`): two more columns after FEATURES (before the
lookahead input), `view_windows` and `view_windows_per_cost` (`features(belief=True)`):
the facade gain weighed by the robot's target belief, with prior strength
`policy.belief_strength` (the rule is written in `jaxmripp.spec.belief`). The NumPy
runtime computes them from the windows its robot's classifier reports and those that
arrive with the map deltas (`jaxmripp.runtime.belief`).
"""

from __future__ import annotations

import numpy as np


FEATURES = (
    "dx", "dy", "dz", "x", "y", "z",
    "heading_0", "heading_1", "heading_2", "heading_3",
    "utility_mean", "utility_std", "comm_mean", "comm_std",
    "cost", "budget_after",
    "view_unknown", "view_facade", "view_unknown_per_cost", "view_facade_per_cost",
    "peer_distance",
)  # fmt: skip
AHEAD_FEATURES = ("ahead_rate",)  # appended to FEATURES with policy.ahead_branches > 0
# after FEATURES, before AHEAD_FEATURES, with policy.belief_features
BELIEF_FEATURES = ("view_windows", "view_windows_per_cost")
ROBOT_STATE = (
    "x", "y", "z",
    "heading_0", "heading_1", "heading_2", "heading_3",
    "budget_left", "step",
)  # fmt: skip
N_GLOBAL_EXTRA = 2


def features(ahead: bool = False, belief: bool = False) -> tuple[str, ...]:
    """The policy's input columns: FEATURES, then BELIEF_FEATURES with the belief input,
    then AHEAD_FEATURES with the lookahead input."""
    return FEATURES + (BELIEF_FEATURES if belief else ()) + (AHEAD_FEATURES if ahead else ())


FEATURE_GROUPS = {
    "comm": ("comm_mean", "comm_std"),
    "view": ("view_unknown", "view_facade", "view_unknown_per_cost", "view_facade_per_cost"),
    "intent": ("peer_distance",),
}


def view_value(unknown, facade, facade_weight: float):
    """What a next-best-view planner counts in a view: unknown voxels plus `facade_weight`
    x unknown facade voxels (`jaxmripp.spec.view`), as totals or per unit of cost."""
    return unknown + facade_weight * facade


def nbv_score(features, facade_weight: float):
    """(..., L) the next-best-view score of candidates (..., L, F): `view_value` per unit
    of flight cost. Plain indexing and arithmetic, so NumPy and JAX arrays share it
    (`jaxmripp.evaluation.baselines.nbv_planner`, the runtime's "nbv" mode)."""
    return view_value(features[..., FEATURES.index("view_unknown_per_cost")],
                      features[..., FEATURES.index("view_facade_per_cost")], facade_weight)


def masked_argmax(scores, mask, xp=np):
    """Argmax over the feasible entries of the last axis (the first of equal maxima); 0
    where nothing is feasible. `xp` is numpy or jax.numpy."""
    return xp.argmax(xp.where(mask, scores, -xp.inf), axis=-1)


def input_keep(comm: bool = True, view: bool = True, intent: bool = True,
               ahead: bool = False, belief: bool = False) -> np.ndarray:
    """(F,) float32 1/0 multipliers of the `features(ahead, belief)` columns: 0 for an
    ablated group."""
    dropped = set()
    for group, kept in (("comm", comm), ("view", view), ("intent", intent)):
        if not kept:
            dropped.update(FEATURE_GROUPS[group])
    return np.asarray([0.0 if name in dropped else 1.0 for name in features(ahead, belief)],
                      np.float32)
