"""nbv_ahead (jaxmripp.sim.lookahead, baselines.nbv_ahead_planner): its two-flight values
against a NumPy reference (a brute-force ray walk for the first view, the runtime's view
gain for the second), its one-step limit (discount 0 chooses as nbv_team) and a jitted act on reset
states (feasible actions, one trace).

One compilation per jitted function below, on the smoke world (G = 20, 6 positions).
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config
from jaxmripp.evaluation import baselines, evaluate
from jaxmripp.runtime import view as runtime_view
from jaxmripp.runtime.mapping import FREE, OCCUPIED, UNKNOWN, voxel_of
from jaxmripp.sim import env as envmod, lookahead
from jaxmripp.spec import layout
from jaxmripp.spec import view as spec

ROOT = Path(__file__).resolve().parents[1]
# truncate: the reset maps know little free space, and under known_free few second
# flights would be feasible.
CFG = config.load(ROOT / "tests" / "smoke.yaml", ["safety.flight=truncate"])
PARAMS = evaluate.eval_params(CFG, 4.0)
DYN = evaluate.eval_dynamic(CFG, 4.0, radio_range=math.inf)
FACADE, BRANCHES, ENVS = 2.0, 5, 3


@chex.assert_max_traces(n=1)
def _reset_and_value(key, discount):
    """A reset env, robot 0's two-flight values (it decides first: its own map) and, for
    each of its branches, the second candidates drawn with the key the values used."""
    key_reset, key_ahead = jax.random.split(key)
    obs, state = envmod.reset(key_reset, PARAMS, DYN)
    mine = jax.tree.map(lambda x: x[0], obs)
    c = jax.tree.map(lambda x: x[0], state.candidates)
    search = lookahead.Search(PARAMS, DYN, state.position, state.heard[0], FACADE, discount,
                              BRANCHES)
    occupancy, top = state.occupancy[0], state.building_top[0]
    values, score = lookahead.lookahead_values(search, mine, occupancy, top, key_ahead, c,
                                               state.budget_left[0], flights=2)
    first_gain = mine.features[:, layout.FEATURES.index("view_unknown")] \
        + FACADE * mine.features[:, layout.FEATURES.index("view_facade")]
    rate = jnp.where(mine.mask, first_gain * (PARAMS.candidates.shell[1] / jnp.maximum(
        c.cost, spec.COST_FLOOR)), -jnp.inf)
    _, order = jax.lax.top_k(rate, BRANCHES)
    second = jax.vmap(lambda j, k: lookahead.next_flight(
        search, occupancy, top, c.position[j], c.heading[j], state.budget_left[0] - c.cost[j],
        k)[1])(order, jax.random.split(key_ahead, BRANCHES))
    return obs, state, values, first_gain, order, second, score


@pytest.fixture(scope="module")
def valued():
    run = jax.jit(jax.vmap(_reset_and_value, in_axes=(0, None)))
    keys = jax.random.split(jax.random.PRNGKey(3), ENVS)
    return jax.tree.map(np.asarray, run(keys, jnp.float32(1.0)))


def _seen(codes, position, heading):
    """Flat indices of the unknown voxels a pose sees: each gain ray walked sample by
    sample until it leaves the grid or meets an occupied voxel (jaxmripp.spec.view)."""
    size = PARAMS.size
    offsets, _ = spec.gain_table(PARAMS.sensor.fov_deg, PARAMS.sensor.range, size)
    camera = voxel_of(np.asarray(position, np.float32)[None], size)[0]
    seen = set()
    for ray in offsets[heading]:
        for offset in ray:
            v = camera + offset
            if np.any(v < 0) or np.any(v >= size):
                break
            flat = (v[0] * size + v[1]) * size + v[2]
            if codes[flat] == OCCUPIED:
                break
            if codes[flat] == UNKNOWN:
                seen.add(int(flat))
    return np.fromiter(seen, np.int64)


def test_two_flight_values_match_a_numpy_reference(valued):
    obs, state, values, first_gain, order, second, score = valued
    shell = PARAMS.candidates.shell[1]
    # The returned score is nbv_team's one-step rate, which ranks the followed branches.
    rate = first_gain * (shell / np.maximum(state.candidates.cost[:, 0], spec.COST_FLOOR))
    np.testing.assert_allclose(score[obs.mask[:, 0]], rate[obs.mask[:, 0]], rtol=1e-6)
    lo, hi = PARAMS.candidates.shell
    checked = 0
    for e in range(ENVS):
        mask = obs.mask[e, 0]
        codes = np.asarray(state.occupancy[e, 0]).reshape(-1)
        c = {name: getattr(state.candidates, name)[e, 0] for name in ("position", "heading",
                                                                       "cost")}
        ranked = {int(j): r for r, j in enumerate(order[e]) if mask[j]}
        for j in range(mask.size):
            if j not in ranked:  # infeasible or outside the branches: never taken
                assert values[e, j] == -np.inf
                continue
            s = jax.tree.map(lambda x: x[e, ranked[j]], second)
            after = codes.copy()
            after[_seen(codes, c["position"][j], c["heading"][j])] = FREE
            unknown, facade = runtime_view.view_gain(
                after, state.building_top[e, 0], s.position, s.heading,
                runtime_view.GainModel(PARAMS.sensor.fov_deg, PARAMS.sensor.range),
                PARAMS.size)
            g1 = np.float64(first_gain[e, j])
            both = (g1 + unknown + FACADE * facade) * shell / np.maximum(
                c["cost"][j] + s.cost, spec.COST_FLOOR)
            alone = g1 * shell / max(c["cost"][j], spec.COST_FLOOR)
            expect = max(alone, both[s.valid].max()) if s.valid.any() else alone
            np.testing.assert_allclose(values[e, j], expect, rtol=2e-6, atol=1e-9)
            # Second flights start at the first pose, cost what is left at most.
            gap = np.linalg.norm(s.position[s.valid] - c["position"][j], axis=-1)
            assert np.all((gap == 0) | ((gap >= lo - 1e-6) & (gap <= hi + 1e-6)))
            assert np.all(s.cost[s.valid] <= state.budget_left[e, 0] - c["cost"][j] + 1e-6)
            checked += int(s.valid.any())
    assert checked >= ENVS  # the reference was compared on real second flights


@chex.assert_max_traces(n=1)
def _choices(key, discount):
    """A reset env and nbv_ahead's choices looking two and three flights ahead."""
    obs, state = envmod.reset(key, PARAMS, DYN)
    chosen = [baselines.nbv_ahead_planner(PARAMS, FACADE, discount, BRANCHES, flights).act(
        key, None, obs, state, DYN)[1] for flights in (2, 3)]
    return obs, jnp.stack(chosen)


@pytest.fixture(scope="module")
def chosen():
    run = jax.jit(jax.vmap(_choices, in_axes=(0, None)))
    keys = jax.random.split(jax.random.PRNGKey(4), 8)
    return {d: jax.tree.map(np.asarray, run(keys, jnp.float32(d))) for d in (0.0, 1.0)}


# The choices' program is one of its own (about 13 s): slow. make test keeps the values
# they maximise against the NumPy reference (test_two_flight_values_match_a_numpy_reference)
# and the rated search's values against the runtime (test_ahead_input_matches_the_numpy_runtime).
@pytest.mark.slow
def test_discount_zero_chooses_as_nbv_team_and_all_choices_are_feasible(chosen):
    obs, actions = chosen[0.0]  # actions (worlds, flights 2 and 3, robots)
    robot0 = obs.features[:, 0]  # robot 0 decides on its own observation
    score = np.asarray(baselines.nbv_scores(robot0, FACADE))
    best = np.where(obs.mask[:, 0], score, -np.inf).max(axis=-1)
    for by_flights in (actions[:, 0], actions[:, 1]):
        taken = np.take_along_axis(score, by_flights[:, :1], axis=-1)[:, 0]
        np.testing.assert_allclose(taken, best, rtol=1e-6)
    for d, (obs, actions) in chosen.items():
        for by_flights in (actions[:, 0], actions[:, 1]):
            picked = np.take_along_axis(obs.mask, by_flights[..., None], axis=-1)[..., 0]
            assert np.all(picked | ~obs.mask.any(-1)), d


@pytest.mark.slow
def test_looking_ahead_changes_some_choices(chosen):
    """With discount 1 later flights matter: on 8 worlds x 2 robots some choice differs
    from the one-step choice, for two flights and for three (else dead code)."""
    for flights in (0, 1):
        assert np.any(chosen[0.0][1][:, flights] != chosen[1.0][1][:, flights])


def test_branches_beyond_the_candidates_are_refused():
    with pytest.raises(ValueError, match="branches = 999; allowed: 1 to the candidate count"):
        baselines.nbv_ahead_planner(PARAMS, FACADE, 1.0, 999)
    with pytest.raises(ValueError, match="flights = 1; allowed: 2 or more"):
        baselines.nbv_ahead_planner(PARAMS, FACADE, 1.0, 4, 1)
    with pytest.raises(config.ConfigError, match="eval.nbv_ahead_branches"):
        config.load(ROOT / "tests" / "smoke.yaml", ["eval.nbv_ahead_branches=25",
                                                      "eval.planners=[nbv_ahead]"])


_AHEAD = ["policy.ahead_branches=5", "policy.ahead_discount=1.5",
          "policy.ahead_facade_weight=3", "radio.range=0.5"]
# The lookahead input as nbv_ahead's value, and as nbv_targets': both with the belief's
# inputs, so that they differ in the rating alone and each compiles once for every test.
AHEAD_SETTINGS = {
    "view": [*_AHEAD, "policy.belief_features=true"],
    "rated": [*_AHEAD, "policy.belief_features=true", "policy.ahead_rated=true"],
}
AHEAD_STEPS = 3


@functools.cache
def _episodes_with_ahead(setting: str):
    """A jitted function of keys (8,): for each, a reset and AHEAD_STEPS flights to random
    feasible candidates under AHEAD_SETTINGS[setting]; the last observations, the states
    they were made from and the step keys that drew their lookahead."""
    cfg = config.load(ROOT / "tests" / "smoke.yaml", AHEAD_SETTINGS[setting])
    params, dyn = envmod.EnvParams.from_config(cfg), envmod.DynamicParams.from_config(cfg)

    def episode(key):
        key_reset, key_steps = jax.random.split(key)
        obs, state = envmod.reset(key_reset, params, dyn)

        def flight(carry, key):
            obs, state, _ = carry
            key_pick, key_step = jax.random.split(key)
            scores = jax.random.uniform(key_pick, obs.mask.shape)
            actions = layout.masked_argmax(scores, obs.mask, jnp).astype(jnp.int32)
            obs, state, *_ = envmod.step(key_step, state, actions, params, dyn)
            return (obs, state, key_step), None

        # A scan, not a Python loop: the step compiles once, not once per flight.
        (obs, state, key_step), _ = jax.lax.scan(
            flight, (obs, state, key_steps), jax.random.split(key_steps, AHEAD_STEPS))
        return obs, state, key_step

    return cfg, jax.jit(jax.vmap(episode))


def _run_episodes(setting: str, seed: int):
    cfg, episodes = _episodes_with_ahead(setting)
    out = episodes(jax.random.split(jax.random.PRNGKey(seed), 8))
    assert episodes._cache_size() == 1  # one trace per setting
    return cfg, out


# The unrated input ("view") ships in no policy (pretrained/default reads the rated one),
# and its program compiles for about 20 s: slow.
@pytest.fixture(scope="module", params=[pytest.param("view", marks=pytest.mark.slow), "rated"])
def ahead_episodes(request):
    cfg, (obs, state, step_keys) = _run_episodes(request.param, 11)
    return cfg, jax.tree.map(np.asarray, (obs, state)), step_keys


def test_ahead_input_matches_the_numpy_runtime(ahead_episodes):
    """The env's lookahead input against the runtime's, fed the uniforms the documented
    key derivation gives, on states a few random flights in; rated, the runtime weighs
    the facade by its own belief's facade rates (`jaxmripp.runtime.belief`)."""
    from jaxmripp import export
    from jaxmripp.runtime import belief as runtime_belief
    from jaxmripp.runtime import candidates as runtime_cands
    from jaxmripp.runtime import lookahead as runtime_lookahead
    from jaxmripp.runtime.mapping import OccupancyMap

    cfg, (obs, state), step_keys = ahead_episodes
    params = envmod.EnvParams.from_config(cfg)
    spec = export.runtime_spec(cfg)
    n_inputs = len(spec.features) - 1  # the columns before the lookahead input
    assert obs.features.shape[-1] == n_inputs + 1
    assert np.all(np.isfinite(obs.features))
    draws = runtime_lookahead.draw_shape(spec)
    facade = layout.features(belief=spec.belief_features).index(
        "view_windows" if spec.ahead_rated else "view_facade")
    followed = improved = near_ties = 0
    for e in range(obs.mask.shape[0]):
        robot_keys = jax.random.split(jax.random.fold_in(step_keys[e], 1), params.n_robots)
        for i in range(params.n_robots):
            uniforms = np.stack([np.asarray(jax.random.uniform(k, draws[1:], jnp.float32))
                                 for k in jax.random.split(robot_keys[i], spec.ahead_branches)])
            occupancy = OccupancyMap(params.size)
            occupancy.codes = state.occupancy[e, i].reshape(-1).copy()
            occupancy.top = state.building_top[e, i].copy()
            c = runtime_cands.Candidates(*(getattr(state.candidates, name)[e, i] for name in
                                           ("position", "heading", "cost", "valid")))
            heard = state.position[e][state.heard[e, i]]
            features = obs.features[e, i, :, :n_inputs]
            gain = layout.view_value(features[:, layout.FEATURES.index("view_unknown")],
                                     features[:, facade], np.float32(3.0))
            one_step = np.asarray(runtime_view.per_cost(gain, c.cost, spec.shell[1]))
            if _near_tie(one_step, obs.mask[e, i], spec):
                near_ties += 1
                continue
            rates = None
            if spec.ahead_rated:  # a classifier that is always right: every mapped window
                voxel, valid = state.world.target_voxel[e], state.world.target_valid[e]
                flat = (voxel[:, 0] * params.size + voxel[:, 1]) * params.size + voxel[:, 2]
                occupancy.mark_windows(flat[valid & (occupancy.codes[flat] != UNKNOWN)])
                rates = runtime_belief.facade_rates(occupancy, spec.belief_strength,
                                                    spec.belief_prior, spec.gain_facade)
            ours = runtime_lookahead.ahead_rates(
                uniforms, features, obs.mask[e, i], c, state.budget_left[e, i], occupancy,
                heard, spec, rates)
            env = obs.features[e, i, :, -1]
            np.testing.assert_allclose(ours, env, rtol=1e-6, err_msg=f"env {e} robot {i}")
            assert np.all(env >= one_step * (1 - 1e-6))  # a value is at least its own rate
            followed += int(obs.mask[e, i].any())
            improved += int(np.sum(env > one_step * (1 + 1e-6)))
    # Real two-flight values were compared, not only one-step rates.
    assert followed >= 6 and improved >= 6 and near_ties <= followed


@pytest.mark.slow  # compiles the unrated episodes too
def test_the_rated_input_reads_the_belief_and_the_rest_is_unchanged():
    """On the same episodes, rating the lookahead input changes that column alone (the
    flights, maps and other inputs are the same), and changes it."""
    _, (obs_rated, state_rated, _) = _run_episodes("rated", 3)
    _, (obs_view, state_view, _) = _run_episodes("view", 3)
    np.testing.assert_array_equal(state_rated.occupancy, state_view.occupancy)
    np.testing.assert_array_equal(obs_rated.features[..., :-1], obs_view.features[..., :-1])
    mask = np.asarray(obs_rated.mask)
    assert not np.allclose(np.asarray(obs_rated.features[..., -1])[mask],
                           np.asarray(obs_view.features[..., -1])[mask])


def _near_tie(rate, mask, spec) -> bool:
    """Whether two of the branches + 1 best nonzero one-step rates agree to float32
    rounding: XLA may fuse the view value's multiply-add, so such candidates may be
    followed in either order (jaxmripp.spec.layout)."""
    rate = np.sort(rate[mask])[::-1][:spec.ahead_branches + 1]
    rate = rate[rate > 0]
    return bool(np.any(np.diff(rate) >= -1e-6 * rate[:-1]))


def test_ahead_input_is_off_by_default_and_bounded_by_the_candidates():
    assert envmod.EnvParams.from_config(CFG).n_features == len(layout.FEATURES)
    with pytest.raises(config.ConfigError, match="policy.ahead_branches"):
        config.load(ROOT / "tests" / "smoke.yaml", ["policy.ahead_branches=25"])
    with pytest.raises(config.ConfigError, match="policy.ahead_rated"):
        config.load(ROOT / "tests" / "smoke.yaml", ["policy.ahead_branches=5",
                                                    "policy.ahead_rated=true"])
