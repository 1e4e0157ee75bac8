"""Whole episodes in the JAX env with every robot driven by the NumPy onboard runtime.

Each robot's `OnboardPlanner` learns only what a real robot would: its own camera (the
env's `sensing.cast` for that robot at its pose), the radio messages of the robots within range (built by the runtime,
delivered along the env's single-hop contacts: the first broadcast, the map deltas of
`radio.share_maps`, then the intents) and whether its last move was blocked. Candidate
poses are the env's (`state.candidates` of that robot), so the two sides choose among the
same poses; everything else -- map, building tops, budget, GPs, features, the decision,
the safety filter and the hold rule of `jaxmripp.spec.flight` -- the runtime computes
itself. The env applies its own hold rule to the chosen actions; the robots it holds must
be the ones whose `resolve` held.

Greedy ties. `baselines.greedy_planner` breaks ties with 1e-5 x uniform noise drawn from the
step's key. Exact ties are structural, not rare: two headings at the same angle from every
pose in a GP get bit-identical kernel rows, so no choice of kappa / lambda avoids them. The
runtime is therefore given the same noise (`tie_break`, derived from the same key as the
JAX planner's) and must then pick the same candidate. What can still differ is float32
rounding of the GP features (measured below: at most a few 1e-6, on the utility std near
zero variance); a flip needs two candidates within that distance after the noise, which
did not happen in any seed we ran (the test prints the smallest JAX margin it met).
"""

from __future__ import annotations

import functools
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.evaluation import baselines
from jaxmripp.sim.observation import in_sectors
from jaxmripp.sim import comms, env as envmod, sensing
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp import config, export
from jaxmripp.runtime import Candidates, OnboardPlanner
from jaxmripp.spec.grid import FREE, OCCUPIED, UNKNOWN
from jaxmripp.spec.layout import FEATURES
from test_runtime import REPO, init_params
from test_runtime_flight import interval_reference

# Also test_runtime_parity's environment: the worker that runs both files
# (tests/conftest.py) builds its programs once, through make_sim. gp.catchup_rounds = 0
# leaves the feeding 2 rounds for 2 peers and none to catch up, so backlogs build up and
# which peer each round picks matters (the parity episodes check the picks).
CFG = config.load(REPO / "tests/smoke.yaml", [
    "world.size=30", "robots.count=3", "robots.budget=[4.0, 4.0]",
    "candidates.positions=8", "candidates.oversample=3", "gp.catchup_rounds=0"])
KAPPA, LAM = 1.0, 0.5  # both GPs enter the score
UTILITY_MEAN, UTILITY_STD, COMM_MEAN = (baselines.UTILITY_MEAN, baselines.UTILITY_STD,
                                        baselines.COMM_MEAN)
VIEW_GAIN = [FEATURES.index("view_unknown"), FEATURES.index("view_facade")]


# Robots close together and a large d_c: flights conflict, and robots hold.
CROWDED = ["radio.collision_distance=0.1", "robots.pad_spacing=0.11", "robots.count=4",
           "robots.budget=[6.0, 6.0]"]


@functools.cache
def make_sim(cfg):
    params, dyn = EnvParams.from_config(cfg), DynamicParams.from_config(cfg)
    return SimpleNamespace(
        params=params, dyn=dyn, radio_range=cfg.radio.range,
        spec=export.runtime_spec(cfg),
        reset=jax.jit(lambda key: envmod.reset(key, params, dyn)),
        step=jax.jit(lambda key, state, actions: envmod.step(key, state, actions, params, dyn)),
        cast=jax.jit(jax.vmap(lambda w, p, h: sensing.cast(w, p, h, params.sensor, params.size),
                              in_axes=(None, 0, 0))),
        greedy=jax.jit(baselines.greedy_planner(KAPPA, LAM).act),
    )


@pytest.fixture(scope="module")
def sim():
    return make_sim(CFG)


def keys_of(seed, steps):
    """episode.run's key schedule: reset key, then (act, step) keys per step."""
    key_reset, key_run = jax.random.split(jax.random.key(seed))
    return key_reset, [jax.random.split(k) for k in jax.random.split(key_run, steps)]


def jax_greedy_episode(sim, seed):
    """The JAX greedy planner through the same steps: per step (obs, state, actions)."""
    key_reset, keys = keys_of(seed, sim.params.max_steps)
    obs, state = sim.reset(key_reset)
    memory = jnp.zeros((sim.params.n_robots, 1))
    out = []
    for key_act, key_step in keys:
        memory, actions = sim.greedy(key_act, memory, obs, state)
        out.append((jax.tree.map(np.asarray, obs), state, np.asarray(actions)))
        obs, state, *_ = sim.step(key_step, state, actions)
    out.append((jax.tree.map(np.asarray, obs), state, None))
    return out


def sense_all(sim, state, planners, blocked, t):
    """Every robot senses; budgets must be the env's (maps too, after the map exchange:
    `share_maps`)."""
    heading = np.asarray(state.heading)
    cast = jax.tree.map(np.asarray, sim.cast(state.world, state.position, state.heading))
    position = np.asarray(state.position)
    for i, planner in enumerate(planners):
        voxels, values = cast.voxels[i], cast.values[i]
        planner.sense(position[i], int(heading[i]), voxels, values,
                      int(cast.seen[i].sum()), blocked=bool(blocked[i]),
                      windows=classified(state.world, voxels, values))
        assert planner.budget_left == pytest.approx(float(state.budget_left[i]), abs=1e-6)


def classified(world, voxels, values):
    """The window voxels among a camera's observed ones (a classifier that is always
    right): the world's valid windows whose voxel it saw OCCUPIED."""
    size = world.height.shape[0]
    target = np.asarray(world.target_voxel)[np.asarray(world.target_valid)]
    flat = (target[:, 0] * size + target[:, 1]) * size + target[:, 2]
    return np.intersect1d(flat, np.asarray(voxels)[np.asarray(values) == OCCUPIED])


def share_maps(state, planners, contact, t, traffic=None):
    """With `radio.share_maps` every robot sends its map deltas along the contacts and
    merges those sent to it; then maps and building tops must be the env's (its merge),
    and no delta ever disagreed with its receiver's map (maps true to the world: the
    runtime's rule that OCCUPIED is never freed changes nothing in honest runs).
    traffic, if given, gets (round, sender, receiver, delta voxels, voxels the sender
    knows) per delivered delta."""
    if planners[0].spec.share_maps:
        outbox = [planner.map_message() for planner in planners]
        known = [int(np.sum(p.map.codes != UNKNOWN)) for p in planners]
        for i, j in zip(*np.nonzero(contact)):
            message = planners[i].receive_map(outbox[j])
            if traffic is not None:
                traffic.append((t, j, i, len(message.delta_for(i).voxels), known[j]))
    for i, planner in enumerate(planners):
        assert planner.sharing.conflicts == 0, f"step {t} robot {i}: maps disagreed"
        np.testing.assert_array_equal(planner.map.grid, np.asarray(state.occupancy[i]),
                                      err_msg=f"step {t} robot {i}: maps differ")
        np.testing.assert_array_equal(planner.map.top, np.asarray(state.building_top[i]),
                                      err_msg=f"step {t} robot {i}: building tops differ")


def runtime_episode(sim, seed, planners, decide, traffic=None):
    """Steps the env with the planners' decisions. decide(t, i, planner, obs, candidates,
    key_act, state) -> Decision. Returns per step (obs, state, decisions, resolved); checks that
    the robots the env holds are those whose `resolve` held (and `share_maps`' checks)."""
    key_reset, keys = keys_of(seed, sim.params.max_steps)
    obs, state = sim.reset(key_reset)
    n = sim.params.n_robots
    blocked = np.zeros(n, bool)
    out = []
    for t, (key_act, key_step) in enumerate(keys):
        sense_all(sim, state, planners, blocked, t)
        contact = np.asarray(comms.contacts(state.position, sim.radio_range))
        outbox = [planner.message() for planner in planners]
        for i, j in zip(*np.nonzero(contact)):
            planners[i].receive(outbox[j])
        share_maps(state, planners, contact, t, traffic)
        o = jax.tree.map(np.asarray, obs)
        c = jax.tree.map(np.asarray, state.candidates)
        decisions = []
        for i, planner in enumerate(planners):
            offered = Candidates(c.position[i], c.heading[i], c.cost[i], o.mask[i])
            d = decide(t, i, planner, o, offered, key_act, state)
            # The GP's posterior std is the square root of a small difference of float32
            # terms updated by different algorithms on each side: relative 2e-4 allowed.
            np.testing.assert_allclose(d.features, o.features[i], atol=1e-5, rtol=2e-4,
                                       err_msg=f"step {t} robot {i}: features differ")
            # The view gain is integer sums and one float32 scaling on both sides.
            np.testing.assert_array_equal(d.features[:, VIEW_GAIN], o.features[i][:, VIEW_GAIN],
                                          err_msg=f"step {t} robot {i}: view gain differs")
            np.testing.assert_allclose(d.robot_state, o.robot_state[i], atol=1e-6)
            decisions.append(d)
        intents = [planner.intent_message() for planner in planners]
        for i, j in zip(*np.nonzero(contact)):
            planners[i].receive_intent(intents[j])
        resolved = [planner.resolve() for planner in planners]
        out.append((o, state, decisions, resolved))
        # The env gets the decisions themselves and applies its own hold rule.
        actions = jnp.asarray([0 if d.hover else d.index for d in decisions], jnp.int32)
        before = jax.tree.map(np.asarray, state.metrics)
        obs, state, *_ = sim.step(key_step, state, actions)
        after = jax.tree.map(np.asarray, state.metrics)
        ours = [r.hover and not d.hover for d, r in zip(decisions, resolved)]
        np.testing.assert_array_equal(after.held - before.held, ours,
                                      err_msg=f"step {t}: the env held other robots")
        blocked = after.obstacle_collisions > before.obstacle_collisions
        assert not blocked.any(), f"step {t}: a known-free flight entered a building"
    out.append((jax.tree.map(np.asarray, obs), state, None, None))
    return out


def greedy_scores(o, i, jitter):
    f = o.features[i]
    s = f[:, UTILITY_MEAN] + KAPPA * f[:, UTILITY_STD] - LAM * f[:, COMM_MEAN] + jitter
    return np.where(o.mask[i], s, -np.inf)


def greedy_runtime(sim, budget):
    planners = [OnboardPlanner(sim.spec, i, budget, team_size=sim.params.n_robots,
                               mode="greedy", kappa=KAPPA, lam=LAM)
                for i in range(sim.params.n_robots)]

    def decide(t, i, planner, o, offered, key_act, state):
        # The JAX planner's tie-break noise for this step, from the same key.
        jitter = np.asarray(1e-5 * jax.random.uniform(key_act, o.mask.shape))
        return planner.decide(candidates=offered, tie_break=jitter[i])

    return planners, decide


# Half a minute per episode, so out of `make test`: test_runtime_parity follows greedy and
# sampled teams round by round on more seeds, test_runtime_sharing checks the deltas.
@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_runtime_team_follows_the_jax_greedy_trajectory(sim, seed):
    reference = jax_greedy_episode(sim, seed)
    budget = float(reference[0][1].budget_initial)
    planners, decide = greedy_runtime(sim, budget)
    traffic = []
    ours = runtime_episode(sim, seed, planners, decide, traffic)
    # Maps were shared (and equal the env's every round, in `share_maps`); after a pair's
    # first contact a delta carries less than the sender's whole map.
    assert sim.spec.share_maps
    first, later = set(), []
    for t, j, i, delta, known in traffic:
        if (j, i) in first:
            later.append(delta / known)
            assert delta < known, f"step {t}: robot {j} sent robot {i} its whole map again"
        first.add((j, i))
    assert len(later) >= 5
    print(f"seed {seed}: {len(traffic)} deltas, after the first contact a mean "
          f"{np.mean(later):.1%} of the sender's known voxels")

    margins, moves = [], 0
    _, key_steps = keys_of(seed, sim.params.max_steps)
    for t, ((o, state, actions), (_, our_state, decisions, _)) in enumerate(
            zip(reference, ours)):
        np.testing.assert_array_equal(np.asarray(our_state.position), np.asarray(state.position))
        np.testing.assert_array_equal(np.asarray(our_state.heading), np.asarray(state.heading))
        if actions is None:
            break
        jitter = np.asarray(1e-5 * jax.random.uniform(key_steps[t][0], o.mask.shape))
        for i, d in enumerate(decisions):
            if not o.mask[i].any():
                assert d.hover, f"step {t} robot {i}: the env retired it, the runtime did not"
                continue
            scores = np.sort(greedy_scores(o, i, jitter[i]))
            if o.mask[i].sum() > 1:
                margins.append(scores[-1] - scores[-2])
            assert d.index == actions[i], (
                f"step {t} robot {i}: runtime chose {d.index} ({d.reason}), JAX greedy "
                f"{actions[i]}; JAX margin {scores[-1] - scores[-2]:.2e}")
            moves += 1
    assert moves >= 10  # the episode really flew
    print(f"seed {seed}: {moves} decisions agree; smallest JAX margin {min(margins):.2e}")


def point_to_segment(point, a, b) -> float:
    """Least distance from a point to the segment a -> b (float64): the closest approach of
    a flight to a robot hovering at `point`, whatever the speed."""
    point, a, b = (np.asarray(x, np.float64) for x in (point, a, b))
    d = b - a
    t = 0.0 if not d.any() else float(np.clip((point - a) @ d / (d @ d), 0.0, 1.0))
    return float(np.linalg.norm(a + t * d - point))


@pytest.mark.parametrize("seed", [2, 3])
def test_safety_filter_passes_exactly_what_the_rules_allow(sim, seed):
    """Every candidate the env offers passes the runtime's filter, and by an independent
    reading of the rules each one is allowed: every voxel its line of flight traverses
    (an exact interval test per voxel) is FREE in the robot's map, and the flight keeps
    more than d_c from every robot heard. The runtime then picks JAX greedy's best."""
    obs, state = sim.reset(keys_of(seed, 1)[0])
    planners, decide = greedy_runtime(sim, float(state.budget_initial))
    ours = runtime_episode(sim, seed, planners, decide)
    _, key_steps = keys_of(seed, sim.params.max_steps)
    g, d_c, checked, held = sim.params.size, sim.spec.collision_distance, 0, 0
    for t, (o, state, decisions, resolved) in enumerate(ours[:-1]):
        jitter = np.asarray(1e-5 * jax.random.uniform(key_steps[t][0], o.mask.shape))
        c = jax.tree.map(np.asarray, state.candidates)
        position = np.asarray(state.position)
        heard = np.asarray(comms.contacts(state.position, sim.radio_range))
        for i, d in enumerate(decisions):
            where = f"seed {seed} step {t} robot {i}"
            assert not np.any(o.mask[i] & ~d.safe), f"{where}: the filter refused an env pose"
            grid = np.asarray(state.occupancy[i])
            targets = {tuple(x) for x in c.position[i][o.mask[i]].tolist()}
            for target in targets:
                voxels = interval_reference(position[i], np.float32(target), g)
                assert all(grid[v] == FREE for v in voxels), f"{where}: {target} not known free"
                for j in np.nonzero(heard[i])[0]:
                    assert point_to_segment(position[j], position[i], target) > d_c - 1e-6, \
                        f"{where}: {target} passes robot {j}"
                checked += 1
            if not o.mask[i].any():
                assert d.hover
                continue
            assert d.index == int(np.argmax(np.where(o.mask[i], greedy_scores(o, i, jitter[i]),
                                                     -np.inf)))
            held += resolved[i].hover
    assert checked > 50
    print(f"seed {seed}: {checked} offered flights checked, {held} holds")


@pytest.mark.slow  # the parity episodes already check every hold, round by round
def test_the_runtime_holds_exactly_the_robots_the_env_holds():
    """A crowded team: chosen flights conflict, and the higher-id robot of each pair in
    range holds. `runtime_episode` checks every round that the robots whose `resolve`
    held are exactly those the env held (jaxmripp.sim.flight.holds)."""
    cfg = config.load(REPO / "tests/smoke.yaml", [
        "world.size=30", "candidates.positions=8", "candidates.oversample=3"] + CROWDED)
    crowded = make_sim(cfg)
    holds = 0
    for seed in (0, 4):
        obs, state = crowded.reset(keys_of(seed, 1)[0])
        planners, decide = greedy_runtime(crowded, float(state.budget_initial))
        for _, _, decisions, resolved in runtime_episode(crowded, seed, planners, decide)[:-1]:
            for d, r in zip(decisions, resolved):
                if r.hover and not d.hover:
                    holds += 1
                    assert r.reason.startswith(f"hold: yields to robot {r.yields_to}")
    assert holds >= 2, "no robot held: pick other seeds"


@pytest.mark.parametrize("sectors", [False, True], ids=["whole_mask", "sectors"])
def test_exported_policy_on_onboard_features_matches_flax(sim, tmp_path, sectors):
    """The runtime policy's logits, memory and choice are the Flax policy's on the env's
    observation; with sectors on both sides (`OnboardPlanner(sectors=True)`, the JAX
    sweep's `eval.sectors`) also on the same sector-restricted masks."""
    network, params = init_params(CFG, seed=3)
    export.export(CFG, params, tmp_path)
    dyn = sim.dyn
    seed = 4
    obs, state = sim.reset(keys_of(seed, 1)[0])
    planners = [OnboardPlanner.load(tmp_path, i, float(state.budget_initial), sectors=sectors)
                for i in range(3)]
    assert all(p.mode == "policy" for p in planners)
    apply = jax.jit(jax.vmap(network.apply, in_axes=(None, 0, 0)))
    memory = {"flax": jnp.zeros((3, CFG.policy.width))}
    compared, narrowed = [], 0

    def decide(t, i, planner, o, offered, key_act, state):
        nonlocal narrowed
        if i == 0:  # the Flax policy on the env's observation, all robots at once
            seen = in_sectors(o, state, dyn) if sectors else o
            memory["mask"] = np.asarray(seen.mask)
            memory["flax"], logits, _ = apply(params, memory["flax"], seen)
            memory["logits"] = np.asarray(logits)
        d = planner.decide(candidates=offered)
        want, mask = memory["logits"][i], memory["mask"][i]
        np.testing.assert_array_equal(d.mask, mask)
        narrowed += int(np.any(mask != o.mask[i]))
        np.testing.assert_allclose(d.scores[d.mask], want[mask], atol=1e-4)
        np.testing.assert_allclose(planner.memory, np.asarray(memory["flax"][i]), atol=1e-4)
        if mask.any():
            assert d.index == int(np.argmax(np.where(mask, want, -np.inf)))
            compared.append(np.ptp(want[mask]))
        return d

    runtime_episode(sim, seed, planners, decide)
    assert len(compared) >= 10 and np.median(compared) > 0.1  # logits are not degenerate
    # The sector rule restricted some decisions (and only with it on).
    assert (narrowed >= 3) if sectors else (narrowed == 0)


@pytest.mark.slow  # the escape rule of both sides is checked against each other in
# test_runtime_flight and against the unsafe rule in test_candidates; this is the episode
def test_robots_that_met_out_of_range_part_alike_with_escape():
    """safety.escape on both sides: robots that came within d_c while out of radio range
    (rho below the pads' spacing, d_c just under rho) are still offered the flights that
    take them no closer, and the runtime's filter passes every pose the env offers then."""
    cfg = config.load(REPO / "tests/smoke.yaml", [
        "world.size=30", "candidates.positions=8", "candidates.oversample=3",
        "robots.count=4", "robots.budget=[6.0, 6.0]", "robots.pad_spacing=0.16",
        "radio.range=0.15", "radio.collision_distance=0.12", "safety.escape=true"])
    escaping = make_sim(cfg)
    assert escaping.spec.escape
    parted = 0
    for seed in (0, 1, 2):
        obs, state = escaping.reset(keys_of(seed, 1)[0])
        planners, decide = greedy_runtime(escaping, float(state.budget_initial))
        for o, state, decisions, _ in runtime_episode(escaping, seed, planners, decide)[:-1]:
            position = np.asarray(state.position)
            gap = np.linalg.norm(position[:, None] - position[None], axis=-1)
            heard = np.asarray(comms.contacts(state.position, escaping.radio_range))
            for i, d in enumerate(decisions):
                assert not np.any(o.mask[i] & ~d.safe), "the filter refused an env pose"
                close = heard[i] & (gap[i] <= escaping.spec.collision_distance)
                parted += bool(close.any() and o.mask[i].any())
    assert parted >= 1, "no robot met another out of range: pick other seeds"
