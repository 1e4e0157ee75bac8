"""A policy trained with the target belief (`policy.belief_features`), exported and flown
by the NumPy runtime through whole episodes of the JAX env (the harness of
tests/test_runtime_episode.py: each robot senses with the env's camera, a classifier that
is always right names the windows among the voxels it saw, and the radio carries
waypoints, map deltas with their window bits, and intents along the env's contacts).

Every round and robot: the windows the runtime knows are the ones the env's belief counts
(the valid windows whose voxel the robot's map holds), the belief columns equal the env's
bit for bit, every other column to float32 rounding (`runtime_episode`), and the exported
policy's logits, memory and choice equal the Flax policy's on the env's observation. The
radio is the signed one (a team key), so the window bits pass the HMAC path."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config, export
from jaxmripp.runtime import OnboardPlanner, team_key
from jaxmripp.spec.grid import UNKNOWN
from jaxmripp.spec.layout import BELIEF_FEATURES, FEATURES
from test_runtime import REPO, init_params
from test_runtime_episode import keys_of, make_sim, runtime_episode

CFG = config.load(REPO / "tests/smoke.yaml", [
    "world.size=30", "robots.count=3", "robots.budget=[6.0, 6.0]", "episode.max_steps=14",
    "candidates.positions=8", "candidates.oversample=3", "policy.belief_features=true"])
BELIEF = [len(FEATURES) + k for k in range(len(BELIEF_FEATURES))]
FACADE = FEATURES.index("view_facade")


@pytest.fixture(scope="module")
def sim():
    return make_sim(CFG)


def known_windows(state, i) -> np.ndarray:
    """Flat indices of the windows the env's belief counts for robot i."""
    size = CFG.world.size
    voxel = np.asarray(state.world.target_voxel)[np.asarray(state.world.target_valid)]
    grid = np.asarray(state.occupancy[i])
    known = grid[voxel[:, 0], voxel[:, 1], voxel[:, 2]] != UNKNOWN
    return np.sort((voxel[known, 0] * size + voxel[known, 1]) * size + voxel[known, 2])


@pytest.mark.parametrize("seed", [4, 7])
def test_an_exported_belief_policy_flies_as_the_flax_policy_decides(sim, tmp_path, seed):
    network, params = init_params(CFG, seed=3)
    export.export(CFG, params, tmp_path)
    obs, state = sim.reset(keys_of(seed, 1)[0])
    key = team_key(seed)
    planners = [OnboardPlanner.load(tmp_path, i, float(state.budget_initial), team_key=key)
                for i in range(3)]
    assert planners[0].spec.features == FEATURES + BELIEF_FEATURES
    apply = jax.jit(jax.vmap(network.apply, in_axes=(None, 0, 0)))
    memory = {"flax": jnp.zeros((3, CFG.policy.width))}
    seen = {"compared": [], "windows": 0, "weighed": 0, "merged": 0}

    def decide(t, i, planner, o, offered, key_act, state):
        if i == 0:  # the Flax policy on the env's observation, all robots at once
            memory["flax"], logits, _ = apply(params, memory["flax"], o)
            memory["logits"] = np.asarray(logits)
        ours = np.flatnonzero(planner.map.window)
        np.testing.assert_array_equal(ours, known_windows(state, i),
                                      err_msg=f"step {t} robot {i}: known windows differ")
        d = planner.decide(candidates=offered)
        np.testing.assert_array_equal(d.features[:, BELIEF], o.features[i][:, BELIEF],
                                      err_msg=f"step {t} robot {i}: belief columns differ")
        want, mask = memory["logits"][i], o.mask[i]
        np.testing.assert_array_equal(d.mask, mask)
        np.testing.assert_allclose(d.scores[mask], want[mask], atol=1e-4)
        np.testing.assert_allclose(planner.memory, np.asarray(memory["flax"][i]), atol=1e-4)
        if mask.any():
            assert d.index == int(np.argmax(np.where(mask, want, -np.inf)))
            seen["compared"].append(np.ptp(want[mask]))
        seen["windows"] = max(seen["windows"], len(ours))
        seen["weighed"] += int(np.any(d.features[:, BELIEF[0]] != d.features[:, FACADE]))
        return d

    runtime_episode(sim, seed, planners, decide)
    for planner in planners:  # windows arrived in map deltas, signed and taken
        assert sum(planner.rejected_messages.values()) == 0
        seen["merged"] += int(np.any(planner.map.window & (planner.sharing.source >= 0)))
    assert len(seen["compared"]) >= 10 and np.median(seen["compared"]) > 0.1
    print(f"seed {seed}: up to {seen['windows']} windows known, {seen['weighed']} decisions "
          f"with rates off the prior, windows merged by {seen['merged']} robots")
    assert seen["windows"] >= 3 and seen["weighed"] >= 10 and seen["merged"] >= 1, seen
