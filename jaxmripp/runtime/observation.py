"""One robot's policy inputs, in NumPy: the columns and formulas written in
`jaxmripp.spec.layout`.

The rule (which column holds what, how offsets, standard deviations and budget fractions
are normalised) is stated once, in that module's docstring; this is its single-robot
implementation, as `jaxmripp.sim.observation.observe` is its JAX one. Both must produce
the same float32 numbers for the same map, GPs, state and candidates, since the policy
was trained on the env's and flies on these.
"""

from __future__ import annotations

import numpy as np

from jaxmripp.runtime import view
from jaxmripp.runtime.candidates import Candidates
from jaxmripp.runtime.gp import GaussianProcess
from jaxmripp.runtime.mapping import OccupancyMap
from jaxmripp.spec import layout
from jaxmripp.spec.grid import HEADING_ANGLES, N_HEADINGS
from jaxmripp.spec.layout import ROBOT_STATE

F32 = np.float32
BUDGET_FLOOR = 1e-6  # the env's guard against dividing by a zero initial budget


def _fraction_of(budget_initial) -> F32:
    return max(F32(budget_initial), F32(BUDGET_FLOOR))


def candidate_features(c: Candidates, position: np.ndarray, budget_left, budget_initial,
                       max_distance: float, utility_gp: GaussianProcess,
                       comm_gp: GaussianProcess, occupancy: OccupancyMap, heard: np.ndarray,
                       gain: view.GainModel, rates: np.ndarray | None = None) -> np.ndarray:
    """(L, F) float32 per-candidate features, columns in FEATURES order, then with the
    robot's facade rates `rates` (G, G) (`jaxmripp.runtime.belief.facade_rates`) the
    BELIEF_FEATURES.

    max_distance: the shell's outer radius, so dx, dy, dz lie in [-1, 1]; the GP columns
    are the posterior mean and the square root of the latent variance at each pose; the
    view columns read `occupancy` (the merged map and its tops) with the gain's model of
    the sensor; heard: (M, 3) positions of the robots heard this round.
    """
    poses = np.concatenate([c.position, HEADING_ANGLES[c.heading][:, None]], axis=1)
    u_mean, u_var = utility_gp.predict(poses)
    c_mean, c_var = comm_gp.predict(poses)
    budget = _fraction_of(budget_initial)
    unknown, facade, *windows = view.view_gain(occupancy.codes, occupancy.top, c.position,
                                               c.heading, gain, occupancy.size, rates=rates)
    belief = [] if rates is None else [
        windows[0][:, None], view.per_cost(windows[0], c.cost, max_distance)[:, None]]
    features = np.concatenate([
        (c.position - position) / F32(max_distance),
        c.position,
        np.eye(N_HEADINGS, dtype=F32)[c.heading],
        u_mean[:, None], np.sqrt(u_var)[:, None],
        c_mean[:, None], np.sqrt(c_var)[:, None],
        c.cost[:, None],
        ((F32(budget_left) - c.cost) / budget)[:, None],
        unknown[:, None], facade[:, None],
        view.per_cost(unknown, c.cost, max_distance)[:, None],
        view.per_cost(facade, c.cost, max_distance)[:, None],
        view.peer_distance(c.position, heard, max_distance)[:, None],
        *belief,
    ], axis=1).astype(F32)
    # A column added here must be added to the spec.
    assert features.shape[1] == len(layout.features(belief=rates is not None))
    return features


def robot_state(position: np.ndarray, heading: int, budget_left, budget_initial, step: int,
                max_steps: int) -> np.ndarray:
    """(S,) float32 robot state, columns in ROBOT_STATE order."""
    state = np.concatenate([
        position,
        np.eye(N_HEADINGS, dtype=F32)[heading],
        [F32(budget_left) / _fraction_of(budget_initial)],
        [F32(step) / F32(max_steps)],
    ]).astype(F32)
    assert state.shape == (len(ROBOT_STATE),)
    return state
