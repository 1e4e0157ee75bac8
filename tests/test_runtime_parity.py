"""Parity of the onboard runtime with the JAX env when the runtime samples its OWN candidates.

tests/test_runtime_episode.py hands the env's candidates to the runtime, so it never
exercises the runtime's sampler in a real episode. Here every robot's `OnboardPlanner`
decides among candidates it drew itself, and the env flies exactly that decision (the
runtime's candidate sets are put into the env state before its step, so the action index
points at the runtime's pose). Both sides then stand in the same state every round --
same maps, budgets, histories, radio contacts, GPs -- and are compared there.

What must agree exactly or to float32 rounding, every round and robot:
- the map (after the map deltas of `radio.share_maps`), building tops and budget the
  runtime keeps equal the env's;
- both candidate sets obey the written rules of `jaxmripp.spec` and docs/design.md section 1,
  checked by an independent implementation here: 4 headings per slot, cost = distance +
  turn cost, kept slots first, padding at the robot, and a pose valid exactly when it is
  inside the world, on the shell (or the robot's own position for a turn), known free
  (every voxel its line of flight traverses, `jaxmripp.spec.grid`, is FREE in the robot's
  map: an exact interval test per voxel here), its flight keeps more than d_c from every
  robot heard (`jaxmripp.spec.flight`: a point-to-segment distance here), within the
  budget, and not the current pose;
- the robots the env holds for a conflicting intent are exactly those whose `resolve`
  held (the runtime's intents travel along the env's contacts); the episodes meet such
  holds (asserted), so the intent rule is compared in the fast suite;
- the runtime's radio is the authenticated one (a team key): every message of an honest
  team is taken, none refused, and no merged map delta ever disagrees with the receiver's
  map (`MapSharing.conflicts`), so the runtime's merge rule (OCCUPIED is never freed)
  gives the env's merge;
- the observation features the runtime builds for the env's candidate set equal the env's
  observation (so the two implementations of `jaxmripp.spec.layout` agree), and each
  env column means what the layout says (dx is the offset over the shell radius, ...);
- the GPs hold the same points in the same slots (the feeding rule of
  `jaxmripp.spec.feeding`), so the GP columns at the runtime's own candidates equal the
  JAX GPs' predictions there.

What cannot agree exactly: the draws. The runtime uses NumPy's generator, the env JAX's
threefry keys, so the two candidate sets of one round are different samples of the same
distribution (tests/test_runtime.py checks that equal uniforms give equal candidates).
For those, pooled over all rounds, the distributions are compared instead: distance on the
shell, direction (elevation, azimuth) and the number of kept slots (two-sample
Kolmogorov-Smirnov and paired means), each drawn from the same states on both sides.
"""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxmripp import export
from jaxmripp.runtime import Candidates, OnboardPlanner, team_key
from jaxmripp.sim import candidates as jax_candidates
from jaxmripp.sim import comms, gp as jax_gp
from jaxmripp.spec.grid import FREE, HEADING_ANGLES, N_HEADINGS
from test_runtime import EXPECTED_FEATURES, EXPECTED_ROBOT_STATE, REPO
from test_runtime_episode import CFG, make_sim, point_to_segment, share_maps
from test_runtime_flight import interval_reference

SEEDS = tuple(range(8))  # the episodes are cheap next to compiling the env
KAPPA, LAM = 1.0, 0.5  # both GPs enter the greedy score
COL = {name: k for k, name in enumerate(EXPECTED_FEATURES)}
STATE = {name: k for k, name in enumerate(EXPECTED_ROBOT_STATE)}
ALPHA = 1e-3  # KS tests: the draws are fixed by the seeds, this only sets how strict


class JaxSide:
    """Every call into the JAX env and its parts, in one place."""

    def __init__(self, cfg):
        sim = make_sim(cfg)  # test_runtime_episode's programs, the same environment
        self.params = p = sim.params
        self.radio_range = sim.radio_range
        self._reset, self._step, self._cast = sim.reset, sim.step, sim.cast
        self._predict = jax.jit(lambda g, poses: jax_gp.predict(g, poses, p.gp))

    def reset(self, seed):
        return self._reset(jax.random.key(seed))

    def step(self, seed, t, state, candidates, actions):
        """Steps with the runtime's candidate sets in place of the env's own."""
        state = state.replace(candidates=jax_candidates.Candidates(
            *(jnp.asarray(np.stack(x)) for x in zip(*candidates))))
        key = jax.random.fold_in(jax.random.key(seed), t + 1)
        obs, state, *_ = self._step(key, state, jnp.asarray(actions, jnp.int32))
        return obs, state

    def camera(self, state):
        return jax.tree.map(np.asarray, self._cast(state.world, state.position, state.heading))

    def contacts(self, state):
        return np.asarray(comms.contacts(state.position, self.radio_range))

    def predict(self, gp_state, poses):
        return tuple(np.asarray(x) for x in self._predict(gp_state, poses))


@pytest.fixture(scope="module")
def sim():
    return SimpleNamespace(jax=JaxSide(CFG), spec=export.runtime_spec(CFG))


def robot(tree, i):
    """Robot i's slice of a NumPy copy of an env pytree (candidates, a GP state)."""
    return jax.tree.map(lambda x: x[i], tree)


# ---------------------------------------------------------------------------------------
# The candidate rules, written again from the spec (not calling either implementation)


def feasible(c, q, heading, budget_left, occupancy, others, spec):
    """(L,) bool: which of the poses c may be offered, by the written rules."""
    g, (lo, hi) = spec.size, spec.shell
    gap = np.linalg.norm(c.position - q, axis=-1)
    inside = np.all((c.position >= 0) & (c.position <= 1), axis=-1)
    on_shell = (gap == 0) | ((gap >= lo - 1e-5) & (gap <= hi + 1e-5))
    clear, apart = np.zeros(len(gap), bool), np.zeros(len(gap), bool)
    for k, target in enumerate(c.position):
        if k % N_HEADINGS:  # a slot's four poses share one position
            clear[k], apart[k] = clear[k - 1], apart[k - 1]
            continue
        clear[k] = inside[k] and all(occupancy[v] == FREE
                                     for v in interval_reference(q, target, g))
        apart[k] = all(point_to_segment(other, q, target) > spec.collision_distance
                       for other in others)
    current = (gap == 0) & (c.heading == heading)
    return inside & on_shell & clear & apart & (c.cost <= budget_left) & ~current


def check_rules(c, q, heading, budget_left, occupancy, others, spec, where):
    k = spec.positions
    np.testing.assert_array_equal(c.heading, np.tile(np.arange(N_HEADINGS), k), err_msg=where)
    slots = c.position.reshape(k, N_HEADINGS, 3)
    assert np.all(slots == slots[:, :1]), f"{where}: a slot's four poses differ in position"
    turn = (c.heading != heading).astype(np.float32)
    cost = np.linalg.norm(c.position - q, axis=-1) + np.float32(spec.turn_cost) * turn
    np.testing.assert_allclose(c.cost, cost, atol=1e-6, err_msg=f"{where}: cost")
    kept = c.valid.reshape(k, N_HEADINGS).any(axis=1)
    assert not np.any(kept[1:] & ~kept[:-1]), f"{where}: kept slots are not first"
    assert np.all(slots[~kept] == q), f"{where}: padding is not at the robot"
    ok = feasible(c, q, heading, budget_left, occupancy, others, spec)
    bad = np.nonzero(c.valid & ~ok)[0]
    assert not bad.size, f"{where}: poses {bad} offered against the rules"
    # A kept position offers every heading the rules allow (none is dropped on the way).
    allowed = np.repeat(kept, N_HEADINGS)
    np.testing.assert_array_equal(c.valid[allowed], ok[allowed], err_msg=where)
    return kept.sum()


def check_column_meaning(features, robot_state, c, q, heading, budget_left, budget_initial,
                         step, spec, others):
    """The env's observation holds, column by column, what jaxmripp.spec.layout says."""
    f, b = features, max(np.float32(budget_initial), np.float32(1e-6))
    dx = [COL["dx"], COL["dy"], COL["dz"]]
    np.testing.assert_allclose(f[:, dx], (c.position - q) / np.float32(spec.shell[1]),
                               atol=1e-6)
    np.testing.assert_array_equal(f[:, [COL["x"], COL["y"], COL["z"]]], c.position)
    onehot = [COL[f"heading_{h}"] for h in range(N_HEADINGS)]
    np.testing.assert_array_equal(f[:, onehot], np.eye(N_HEADINGS)[c.heading])
    np.testing.assert_array_equal(f[:, COL["cost"]], c.cost)
    np.testing.assert_allclose(f[:, COL["budget_after"]], (budget_left - c.cost) / b,
                               atol=1e-6)
    assert np.all(f[:, COL["utility_std"]] >= 0) and np.all(f[:, COL["comm_std"]] >= 0)
    shell = np.float32(spec.shell[1])
    for gain in ("view_unknown", "view_facade"):
        assert np.all((f[:, COL[gain]] >= 0) & (f[:, COL[gain]] <= 1))
        np.testing.assert_allclose(f[:, COL[f"{gain}_per_cost"]], f[:, COL[gain]] * shell
                                   / np.maximum(c.cost, 1e-3), rtol=1e-6)
    assert np.all(f[:, COL["view_facade"]] <= f[:, COL["view_unknown"]])
    gaps = [np.linalg.norm(c.position - other, axis=-1) / shell for other in others]
    np.testing.assert_allclose(f[:, COL["peer_distance"]], np.minimum(np.min(
        gaps, axis=0), 5.0) if gaps else 5.0, rtol=1e-6)
    s = robot_state
    np.testing.assert_array_equal(s[[STATE["x"], STATE["y"], STATE["z"]]], q)
    np.testing.assert_array_equal(s[[STATE[f"heading_{h}"] for h in range(N_HEADINGS)]],
                                  np.eye(N_HEADINGS)[heading])
    assert s[STATE["budget_left"]] == pytest.approx(budget_left / b, abs=1e-6)
    assert s[STATE["step"]] == pytest.approx(step / CFG.episode.max_steps)


def check_gps(planner, utility_gp, comm_gp, where):
    """Same points in the same slots: the feeding order agrees (spec.feeding)."""
    for ours, theirs, name in ((planner.utility_gp, utility_gp, "utility"),
                               (planner.comm_gp, comm_gp, "comm")):
        for field in ("inputs", "targets", "valid", "stamp"):
            np.testing.assert_array_equal(getattr(ours, field), getattr(theirs, field),
                                          err_msg=f"{where}: {name} GP {field}")


def draws(c, q):
    """Distance, elevation (z of the unit direction) and azimuth of the kept drawn slots."""
    slots = c.position.reshape(-1, N_HEADINGS, 3)[c.valid.reshape(-1, N_HEADINGS).any(1), 0]
    offset = slots - q
    gap = np.linalg.norm(offset, axis=-1)
    offset, gap = offset[gap > 0], gap[gap > 0]  # the turn in place is not a draw
    return np.stack([gap, offset[:, 2] / gap, np.arctan2(offset[:, 1], offset[:, 0])], 1)


# ---------------------------------------------------------------------------------------
# The episodes


def fly_episode(sim, seed, pooled):
    """One episode flown by runtime-sampled decisions; checks every round, pools draws.
    Returns the number of decisions checked."""
    spec, jx = sim.spec, sim.jax
    obs, state = jx.reset(seed)
    n = jx.params.n_robots
    key = team_key(seed)
    planners = [OnboardPlanner(spec, i, float(state.budget_initial), team_size=n,
                               mode="greedy", kappa=KAPPA, lam=LAM, seed=1000 * seed + i,
                               team_key=key)
                for i in range(n)]
    blocked, checked = np.zeros(n, bool), 0
    for t in range(jx.params.max_steps):
        now = jax.tree.map(np.asarray, state)  # one transfer per round
        if now.done.all():
            break
        contact = sense_and_talk(jx, now, planners, blocked, t)
        o = jax.tree.map(np.asarray, obs)
        decisions = []
        for i, planner in enumerate(planners):
            if now.done[i]:
                # The env retires a robot without candidates; the runtime would keep
                # trying. Keep the two in step: no decision, but this round's feeding.
                planner.feed_gps()
                check_gps(planner, robot(now.utility_gp, i), robot(now.comm_gp, i),
                          f"seed {seed} round {t} robot {i} (retired)")
                decisions.append(None)
            else:
                decisions.append(planner.decide())
                check_round(sim, now, o, planner, decisions[-1], i, t, seed, pooled)
                checked += 1
        held = exchange_intents(planners, decisions, contact)
        chosen, actions = [], []
        for i, d in enumerate(decisions):
            fly = d is not None and not d.hover  # the env applies its own hold rule
            c = d.candidates if d is not None else robot(now.candidates, i)
            chosen.append(Candidates(c.position, c.heading, c.cost, c.valid & fly))
            actions.append(d.index if fly else 0)
        obs, state = jx.step(seed, t, state, chosen, actions)
        metrics = jax.tree.map(np.asarray, state.metrics)
        np.testing.assert_array_equal(metrics.held - now.metrics.held, held,
                                      err_msg=f"seed {seed} round {t}: the env held others")
        blocked = metrics.obstacle_collisions > now.metrics.obstacle_collisions
        assert not blocked.any(), f"seed {seed} round {t}: a flight entered a building"
        pooled["held"] += int(held.sum())
    for planner in planners:
        assert sum(planner.rejected_messages.values()) == 0, planner.rejected_messages
        assert planner.radio.accepted, "no message was taken"
    return checked


def sense_and_talk(jx, now, planners, blocked, t):
    """Senses, exchanges the first broadcast and the map deltas along the env's contacts
    (maps and building tops are then the env's); returns the contacts."""
    cast = jx.camera(now)
    for i, planner in enumerate(planners):
        planner.sense(now.position[i], int(now.heading[i]), cast.voxels[i], cast.values[i],
                      int(cast.seen[i].sum()), blocked=bool(blocked[i]))
        assert planner.budget_left == pytest.approx(float(now.budget_left[i]), abs=1e-6)
    contact = jx.contacts(now)
    outbox = [planner.message() for planner in planners]
    for i, j in zip(*np.nonzero(contact)):
        planners[i].receive(outbox[j])
    share_maps(now, planners, contact, t)
    return contact


def exchange_intents(planners, decisions, contact):
    """The intent broadcast of the robots that decided, then `resolve`: (N,) bool held."""
    deciding = [d is not None for d in decisions]
    intents = [p.intent_message() if ok else None for p, ok in zip(planners, deciding)]
    for i, j in zip(*np.nonzero(contact)):
        if deciding[i] and deciding[j]:
            planners[i].receive_intent(intents[j])
    held = np.zeros(len(planners), bool)
    for i, (planner, d) in enumerate(zip(planners, decisions)):
        if d is not None:
            resolved = planner.resolve()
            held[i] = resolved.hover and not d.hover
    return held


def check_round(sim, now, o, planner, d, i, t, seed, pooled):
    """Every per-round comparison for robot i, whose runtime just decided d."""
    spec, where = sim.spec, f"seed {seed} round {t} robot {i}"
    q, heading, budget_left = now.position[i], int(now.heading[i]), now.budget_left[i]
    others = now.position[sim.jax.contacts(now)[i]]  # the robots it heard this round
    env_c = robot(now.candidates, i)
    # Rules: the runtime's own set and the env's set, by one independent checker.
    kept_ours = check_rules(d.candidates, q, heading, budget_left, now.occupancy[i], others,
                            spec, f"{where} (runtime)")
    kept_env = check_rules(env_c, q, heading, budget_left, now.occupancy[i], others, spec,
                           f"{where} (env)")
    # The layout: the runtime's builder on the env's set gives the env's observation.
    check_column_meaning(o.features[i], o.robot_state[i], env_c, q, heading, budget_left,
                         now.budget_initial, t, spec, others)
    features, robot_state = planner.observe(env_c)
    np.testing.assert_allclose(features, o.features[i], atol=1e-5, err_msg=where)
    np.testing.assert_allclose(robot_state, o.robot_state[i], atol=1e-6, err_msg=where)
    # Feeding: same GP contents, hence the same GP columns at the runtime's own poses.
    utility_gp, comm_gp = robot(now.utility_gp, i), robot(now.comm_gp, i)
    check_gps(planner, utility_gp, comm_gp, where)
    poses = np.concatenate([d.candidates.position,
                            HEADING_ANGLES[d.candidates.heading][:, None]], 1)
    for gp_state, mean, std in ((utility_gp, "utility_mean", "utility_std"),
                                (comm_gp, "comm_mean", "comm_std")):
        want_mean, want_var = sim.jax.predict(gp_state, poses)
        np.testing.assert_allclose(d.features[:, COL[mean]], want_mean, atol=1e-5,
                                   err_msg=f"{where}: {mean}")
        np.testing.assert_allclose(d.features[:, COL[std]], np.sqrt(want_var), atol=1e-5,
                                   err_msg=f"{where}: {std}")
    pooled["kept"].append((kept_ours, kept_env))
    pooled["ours"].append(draws(d.candidates, q))
    pooled["env"].append(draws(env_c, q))


@pytest.fixture(scope="module")
def pooled(sim):
    """Flies every seed once (all per-round checks run here) and pools the draws."""
    pooled = {"kept": [], "ours": [], "env": [], "held": 0}
    checked = [fly_episode(sim, seed, pooled) for seed in SEEDS]
    print(f"{sum(checked)} decisions checked, {pooled['held']} holds")
    return SimpleNamespace(checked=checked, held=pooled["held"],
                           kept=np.asarray(pooled["kept"]),
                           ours=np.concatenate(pooled["ours"]),
                           env=np.concatenate(pooled["env"]))


def test_runtime_sampled_episodes_agree_with_the_env_round_by_round(pooled):
    # Every per-round check passed (in the fixture) on enough decisions of every seed.
    assert min(pooled.checked) >= CFG.robots.count, pooled.checked
    assert sum(pooled.checked) >= 0.5 * len(SEEDS) * CFG.robots.count \
        * CFG.episode.max_steps, pooled.checked
    # Some flights conflicted and were held, on both sides alike (checked every round).
    assert pooled.held >= 1, "no robot held: the intent rule went uncompared"


def test_runtime_draws_follow_the_env_distribution(pooled):
    ours, env = pooled.ours, pooled.env
    assert len(ours) > 200 and len(env) > 200, (len(ours), len(env))
    for column, name in enumerate(("distance", "elevation", "azimuth")):
        result = stats.ks_2samp(ours[:, column], env[:, column])
        print(f"{name}: KS {result.statistic:.3f} (p = {result.pvalue:.3g}, "
              f"{len(ours)} vs {len(env)} draws)")
        assert result.pvalue > ALPHA, f"{name} distributions differ: {result}"
    # Kept slots per round, paired (the same state on both sides).
    diff = pooled.kept[:, 0] - pooled.kept[:, 1]
    se = diff.std(ddof=1) / np.sqrt(len(diff))
    print(f"kept slots: runtime {pooled.kept[:, 0].mean():.2f}, env "
          f"{pooled.kept[:, 1].mean():.2f} (paired difference SE {se:.2f})")
    assert abs(diff.mean()) <= max(4 * se, 0.25)
