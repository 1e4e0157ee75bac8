"""The NumPy onboard runtime: export format, ports of the GP / candidates, radio messages,
safety filter and bad input. The safe-flight rules (traversal, closest approach, take-off
scan, intents and holds, budget and intent messages) are in tests/test_runtime_flight.py,
shared maps and the view gain in tests/test_runtime_sharing.py; whole-episode parity with
the JAX env lives in tests/test_runtime_episode.py (env candidates) and
tests/test_runtime_parity.py (the runtime's own), the NumPy-only guarantee in
tests/test_runtime_numpy_only.py and the exporter in tests/test_export.py."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.sim import candidates as jax_candidates
from jaxmripp import config, export
from jaxmripp.sim import gp as jax_gp, observation
from jaxmripp.sim.params import EnvParams
from jaxmripp.learn import policy as policymod, ppo
from jaxmripp.config import GPConfig, SafetyConfig
from jaxmripp.runtime import (Candidates, CorruptWeightsError, InvalidPoseError, MessageError,
                              OnboardPlanner, PlannerStateError, ProtocolVersionError,
                              RuntimeSpec, WeightsFormatError)
from jaxmripp.runtime import FEATURES, ROBOT_STATE
from jaxmripp.runtime import candidates as np_candidates
from jaxmripp.runtime import flight, messages, view, weights
from jaxmripp.runtime.gp import GaussianProcess, evaluation_poses
from jaxmripp.runtime.mapping import FREE, OCCUPIED, UNKNOWN, OccupancyMap

REPO = Path(__file__).resolve().parents[1]
CFG = config.load(REPO / "tests/smoke.yaml", ["world.size=30", "robots.count=3"])


def spec_of(cfg=CFG) -> RuntimeSpec:
    return export.runtime_spec(cfg)


def init_params(cfg=CFG, seed=0, noise=0.1):
    """Flax params of cfg's policy, with weight noise so no output is degenerate."""
    network = ppo.make_network(cfg)
    n_cand = cfg.candidates.count
    obs = observation.Observation(
        features=jnp.zeros((n_cand, EnvParams.from_config(cfg).n_features)),
        mask=jnp.ones((n_cand,), bool),
        robot_state=jnp.zeros((observation.N_ROBOT_STATE,)),
        global_state=jnp.zeros((observation.global_state_size(cfg.robots.count),)))
    params = jax.jit(network.init)(jax.random.key(seed), policymod.initial_memory(cfg.policy), obs)
    rng = np.random.default_rng(seed)
    noisy = lambda x: np.float32(np.asarray(x) + noise * rng.normal(size=x.shape))  # noqa: E731
    return network, jax.tree.map(noisy, params)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    network, params = init_params()
    out = tmp_path_factory.mktemp("export")
    npz, header = export.export(CFG, params, out)
    return out, network, params


def sense_free(planner, position=(0.5, 0.5, 0.5), heading=1, n_seen=0):
    """Senses a world seen to be FREE everywhere (flights need known-free voxels)."""
    g = planner.spec.size
    planner.sense(np.asarray(position, np.float32), heading, np.arange(g ** 3),
                  np.zeros(g ** 3, np.int8), n_seen)


# ---------------------------------------------------------------------------------------
# Export format


# The policy's input columns written out independently of jaxmripp.spec.layout (which the
# env, the exporter and the runtime all import): a column renamed, added or moved there
# must be changed here too, on purpose. What each column holds is checked against the
# env's observe in tests/test_runtime_parity.py.
EXPECTED_FEATURES = [
    "dx", "dy", "dz", "x", "y", "z", "heading_0", "heading_1", "heading_2", "heading_3",
    "utility_mean", "utility_std", "comm_mean", "comm_std", "cost", "budget_after",
    "view_unknown", "view_facade", "view_unknown_per_cost", "view_facade_per_cost",
    "peer_distance"]
EXPECTED_ROBOT_STATE = [
    "x", "y", "z", "heading_0", "heading_1", "heading_2", "heading_3", "budget_left", "step"]


def test_layout_and_header_match_the_written_layout(exported):
    assert list(FEATURES) == EXPECTED_FEATURES
    assert list(ROBOT_STATE) == EXPECTED_ROBOT_STATE
    out, network, params = exported
    header = json.loads((out / "policy.json").read_text())
    assert header["format_version"] == weights.FORMAT_VERSION
    assert header["layout"] == {"features": EXPECTED_FEATURES,
                                "robot_state": EXPECTED_ROBOT_STATE}
    # The network the env trains reads exactly that many columns.
    flat = policymod.flatten_params(params)
    assert flat["embed/kernel"].shape[0] == len(EXPECTED_FEATURES)
    assert flat["state_embed/kernel"].shape[0] == len(EXPECTED_ROBOT_STATE)
    assert header["policy"] == policymod.runtime_config(CFG.policy)
    c = header["config"]
    assert c["world"]["size"] == 30 and c["radio"]["range"] == CFG.radio.range
    assert c["candidates"]["shell"] == list(CFG.candidates.shell)
    assert c["gp"]["capacity"] == CFG.gp.capacity and c["reward"]["utility_norm"] == 16.0
    assert c["robots"]["turn_cost"] == CFG.robots.turn_cost
    assert c["safety"] == {"flight": CFG.safety.flight, "escape": CFG.safety.escape}
    assert c["radio"]["share_maps"] is CFG.radio.share_maps is True
    assert c["sensor"]["fov_deg"] == CFG.sensor.fov_deg
    spec = spec_of()
    assert (spec.size, spec.n_candidates, spec.gp.capacity) == (30, CFG.candidates.count, 16)
    assert (spec.share_maps, spec.fov_deg, spec.sensor_range) == (
        True, CFG.sensor.fov_deg, CFG.sensor.range)


def test_export_round_trip_is_exact_and_hashed(exported):
    out, _, params = exported
    loaded = weights.load(out)
    flat = policymod.flatten_params(params)
    assert loaded.weights.keys() == flat.keys()
    for name in flat:
        np.testing.assert_array_equal(loaded.weights[name], flat[name])
    assert loaded.header["weights"]["sha256"] == weights.weights_sha256(flat)
    assert loaded.spec == spec_of()


def test_infinite_radio_range_survives_strict_json(tmp_path):
    cfg = config.load(REPO / "tests/smoke.yaml", ["radio.range=.inf"])
    _, params = init_params(cfg)
    export.export(cfg, params, tmp_path)
    text = (tmp_path / "policy.json").read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert weights.load(tmp_path).spec.radio_range == float("inf")


def _copy(exported, tmp_path):
    out, _, _ = exported
    for name in ("policy.npz", "policy.json"):
        (tmp_path / name).write_bytes((out / name).read_bytes())
    return tmp_path


def test_other_format_version_is_refused(exported, tmp_path):
    path = _copy(exported, tmp_path)
    header = json.loads((path / "policy.json").read_text())
    header["format_version"] = weights.FORMAT_VERSION + 1
    (path / "policy.json").write_text(json.dumps(header))
    with pytest.raises(WeightsFormatError, match="format version 2; this runtime reads version 1"):
        OnboardPlanner.load(path, robot_id=0, budget=1.0)


@pytest.mark.parametrize("name", ["policy.npz", "policy.json"])
def test_truncated_files_are_refused(exported, tmp_path, name):
    path = _copy(exported, tmp_path)
    data = (path / name).read_bytes()
    (path / name).write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptWeightsError, match="truncated") as err:
        weights.load(path)
    assert "\n" not in str(err.value)


def test_changed_weights_fail_the_hash(exported, tmp_path):
    path = _copy(exported, tmp_path)
    loaded = weights.load(path)
    changed = dict(loaded.weights)
    changed["embed/bias"] = changed["embed/bias"] + 1.0
    np.savez(path / "policy.npz", **changed)
    with pytest.raises(CorruptWeightsError, match="sha256"):
        weights.load(path)


def test_missing_header_fields_are_named(exported, tmp_path):
    path = _copy(exported, tmp_path)
    header = json.loads((path / "policy.json").read_text())
    del header["config"]["gp"]["noise"]
    (path / "policy.json").write_text(json.dumps(header))
    with pytest.raises(WeightsFormatError, match="config.gp.noise"):
        weights.load(path)


def test_gain_model_travels_in_the_header_and_older_headers_keep_the_default():
    see_through = dataclasses.replace(CFG, sensor=dataclasses.replace(
        CFG.sensor, gain_occlusion=False, gain_facade="column"))
    assert spec_of(see_through).gain == view.GainModel(CFG.sensor.fov_deg, CFG.sensor.range,
                                                        False, "column")
    header = weights.jsonable(export.header(see_through))
    for key in ("gain_occlusion", "gain_facade"):  # exported before these settings
        del header["config"]["sensor"][key]
    assert RuntimeSpec.from_header(header).gain == spec_of().gain == view.GainModel(
        CFG.sensor.fov_deg, CFG.sensor.range, True, "nearby")
    header["config"]["sensor"]["gain_facade"] = "roof"
    with pytest.raises(WeightsFormatError, match="gain_facade 'roof' is not one of nearby, around, column"):
        RuntimeSpec.from_header(header)


# ---------------------------------------------------------------------------------------
# Ports of the JAX math


def test_gp_matches_jax_gp_through_eviction():
    cfg = GPConfig(capacity=8, eval_grid=2)
    spec = spec_of(config.from_dict({"gp": {"capacity": 8, "eval_grid": 2}})).gp
    eval_poses = evaluation_poses(spec)
    np.testing.assert_array_equal(eval_poses, np.asarray(jax_gp.evaluation_poses(cfg)))
    rng = np.random.default_rng(0)
    angles = np.float32([0, np.pi / 2, np.pi, 3 * np.pi / 2])
    poses = np.concatenate([rng.random((20, 3)), angles[rng.integers(0, 4, (20, 1))]],
                           1).astype(np.float32)
    poses[7] = poses[6]  # an exact duplicate pose
    values = rng.random(20).astype(np.float32)
    queries = np.concatenate([rng.random((30, 3)), angles[rng.integers(0, 4, (30, 1))]],
                             1).astype(np.float32)
    queries[:5] = poses[15:]  # at stored points

    add = jax.jit(jax_gp.add, static_argnums=3)
    predict = jax.jit(jax_gp.predict, static_argnums=2)
    state = jax_gp.empty(cfg, jnp.asarray(eval_poses))
    ours = GaussianProcess(spec, eval_poses)
    for i in range(20):  # 20 > 8: the ring buffer evicts 12 times
        state = add(state, poses[i], values[i], cfg, jnp.asarray(eval_poses))
        ours.add(poses[i], values[i])
        mean, var = predict(state, queries, cfg)
        our_mean, our_var = ours.predict(queries)
        np.testing.assert_allclose(our_mean, mean, atol=2e-5)
        np.testing.assert_allclose(our_var, var, atol=2e-5)
        np.testing.assert_allclose(ours.trace, state.trace, rtol=1e-4)
    np.testing.assert_array_equal(ours.valid, state.valid)
    np.testing.assert_array_equal(ours.stamp, state.stamp)
    np.testing.assert_allclose(ours.root, state.root, atol=1e-3)


def test_candidates_match_jax_sampler_given_the_same_uniforms():
    spec = spec_of()
    cand, robots = CFG.candidates, CFG.robots
    g = spec.size
    occupancy = np.full((g, g, g), FREE, np.int8)
    occupancy[14:17, 10:20, :12] = OCCUPIED  # a wall next to the robot
    occupancy[18:22, 18:22, 6:12] = UNKNOWN  # and a patch not seen yet
    # Robot 1 sits where some flights pass it; row 0 is the robot itself.
    others = np.float32([[0.5, 0.5, 0.3], [0.45, 0.4, 0.38], [0.9, 0.9, 0.9]])
    known = np.array([False, True, False])
    sample = jax.jit(jax_candidates.sample, static_argnums=(7, 8, 11))
    our_map = OccupancyMap(g)
    our_map.codes[:] = occupancy.reshape(-1)
    rejected = []
    for seed in range(6):
        key = jax.random.key(seed)
        position, heading, budget = np.float32([0.5, 0.5, 0.3]), seed % 4, 0.2 + 0.05 * seed
        want = jax.tree.map(np.asarray, sample(
            key, position, jnp.int32(heading), jnp.float32(budget), occupancy, others, known,
            cand, SafetyConfig(flight=spec.flight), jnp.float32(robots.turn_cost),
            jnp.float32(spec.collision_distance), g))
        uniforms = np.asarray(jax.random.uniform(key, (cand.positions * cand.oversample - 1, 3)))
        got = np_candidates.sample(uniforms, position, heading, np.float32(budget), our_map,
                                   others[known], spec)
        np.testing.assert_array_equal(got.valid, want.valid)
        np.testing.assert_array_equal(got.heading, want.heading)
        np.testing.assert_allclose(got.position, want.position, atol=1e-6)
        np.testing.assert_allclose(got.cost, want.cost, atol=1e-6)
        rejected.append(int((~got.valid).sum()))
    assert max(rejected) > 0  # the rules did reject something


def test_candidates_and_view_gain_for_many_poses_and_maps_match_one_at_a_time():
    """The lookahead's batched forms (sample_many, view_gain and after_views over B maps)
    give what B separate calls on B separate maps give."""
    spec = spec_of()
    g, rng = spec.size, np.random.default_rng(4)
    base = np.full((g, g, g), UNKNOWN, np.int8)
    base[8:22, 8:22, 6:24] = FREE  # known around the poses, unknown beyond
    base[14:17, 10:20, :12] = OCCUPIED
    top = np.zeros((g, g), np.int8)
    top[14:17, 10:20] = 12
    maps = np.repeat(base.reshape(1, -1), 4, axis=0)
    for b in range(4):  # each map with its own unknown patch among the poses
        maps[b].reshape(g, g, g)[9 + 3 * b:13 + 3 * b, 9:21, 7:22] = UNKNOWN
    position = rng.uniform(0.4, 0.6, (4, 3)).astype(np.float32)
    heading, budget = np.array([0, 1, 2, 3]), np.float32([0.2, 0.3, 0.25, 0.05])
    uniforms = rng.random((4, spec.positions * spec.oversample - 1, 3), np.float32)
    others = np.float32([[0.45, 0.4, 0.38]])
    many = np_candidates.sample_many(uniforms, position, heading, budget, maps, g, others,
                                     spec)
    gains = view.view_gain(maps, top, many.position, many.heading, spec.gain, g)
    # A map with unknown voxels scattered everywhere, so that every pose sees some.
    patchy = np.where(rng.random(g ** 3) < 0.3, UNKNOWN, base.reshape(-1)).astype(np.int8)
    after = view.after_views(patchy, top, position, heading, spec.gain, g)
    margin = after.margin
    # The padded copies hold the map inside OCCUPIED margins; both read the same copies.
    inner = after.codes.reshape(4, g + 2 * margin, g + 2 * margin, g + 2 * margin)[
        :, margin:-margin, margin:-margin, margin:-margin].reshape(4, -1)
    assert np.all(np.delete(after.codes.reshape(4, -1), after.index(
        np.stack(np.unravel_index(np.arange(g ** 3), (g,) * 3), -1)), axis=1) == OCCUPIED)
    many_after = np_candidates.sample_many(uniforms, position, heading, budget, after, g,
                                           others, spec)
    gains_after = view.view_gain(after, top, many.position, many.heading, spec.gain, g)
    for b in range(4):
        one_map = OccupancyMap(g)
        one_map.codes[:] = maps[b]
        one = np_candidates.sample(uniforms[b], position[b], heading[b], budget[b], one_map,
                                   others, spec)
        for got, want in zip(many, one):
            np.testing.assert_array_equal(got[b], want)
        for got, want in zip(gains, view.view_gain(maps[b], top, one.position, one.heading,
                                                   spec.gain, g)):
            np.testing.assert_array_equal(got[b], want)
        # after_views: the map with what pose b sees of it counted as FREE, and no more.
        seen = [view.view_gain(m, top, position[b:b + 1], heading[b:b + 1], spec.gain,
                               g)[0][0] for m in (patchy, inner[b])]
        assert seen[0] > 0 and seen[1] == 0
        changed = inner[b] != patchy
        assert np.all(inner[b][changed] == FREE) and np.all(patchy[changed] == UNKNOWN)
        # Sampling and view gains on the padded copies equal those on plain copies.
        for got, want in zip(many_after, np_candidates.sample_many(
                uniforms[b:b + 1], position[b:b + 1], heading[b:b + 1], budget[b:b + 1],
                inner[b], g, others, spec)):
            np.testing.assert_array_equal(got[b], want[0])
        for got, want in zip(gains_after, view.view_gain(inner[b], top, many.position[b],
                                                         many.heading[b], spec.gain, g)):
            np.testing.assert_array_equal(got[b], want)
    assert any(many.valid[b].sum() != many.valid[0].sum() for b in range(1, 4))


# ---------------------------------------------------------------------------------------
# Map and safety filter


def test_safety_filter_rejects_occupied_paths_and_close_robots_or_hovers_with_a_reason():
    spec = spec_of()
    planner = OnboardPlanner(spec, 0, budget=1.0, team_size=3)
    sense_free(planner)
    # Candidates supplied by the caller: one through a wall, one ending next to robot 1, one
    # ending 0.07 from it but passing 0.04 from it on the way, one through a voxel not
    # seen yet, one fine.
    def obstacles():
        planner.map.grid[17, 15, 15] = OCCUPIED  # a wall
        planner.map.grid[15, 15, 18] = UNKNOWN  # not seen yet

    obstacles()
    peer = OnboardPlanner(spec, 1, budget=1.0, team_size=3)
    sense_free(peer, position=(0.5, 0.3, 0.5))
    planner.receive(peer.message())
    offered = Candidates(np.float32([[0.7, 0.5, 0.5], [0.5, 0.31, 0.5], [0.5, 0.25, 0.55],
                                     [0.5, 0.5, 0.7], [0.5, 0.7, 0.5]]),
                         np.int32([0, 3, 3, 1, 1]), None, None)
    d = planner.decide(candidates=offered)
    np.testing.assert_array_equal(d.safe, [False, False, False, False, True])
    np.testing.assert_array_equal(d.safe, planner.map.known_free(
        planner.position, offered.position, 0.3) & flight.clear_of_robots(
        planner.position, offered.position, peer.position[None], spec.collision_distance))
    assert d.index == 4 and not d.hover and d.reason == "greedy"

    # Nothing safe: it hovers at its pose and says why (it did not fly: stopped at start).
    sense_free(planner)
    obstacles()
    planner.receive(peer.message())
    d = planner.decide(candidates=Candidates(offered.position[:2], offered.heading[:2], None,
                                             None))
    assert d.hover and d.index == -1
    np.testing.assert_array_equal(d.position, planner.position)
    assert "1 cross a voxel not known free" in d.reason
    assert "1 pass within d_c = 0.05 of a robot heard" in d.reason


def test_own_sampling_respects_every_rule():
    spec = spec_of()
    planner = OnboardPlanner(spec, 0, budget=0.5, team_size=3, seed=4)
    sense_free(planner, position=(0.5, 0.5, 0.2))
    peer = OnboardPlanner(spec, 2, budget=1.0, team_size=3)
    sense_free(peer, position=(0.5, 0.65, 0.25))
    planner.receive(peer.message())
    planner.map.grid[15:18, 16:22, :8] = OCCUPIED
    planner.map.grid[10:13, 10:20, 4:9] = UNKNOWN
    for _ in range(5):
        planner.receive(peer.message())  # heard again every round
        d = planner.decide()
        assert not d.hover
        c = d.candidates
        ok = c.valid & d.safe
        assert ok.any()
        gaps = np.linalg.norm(c.position[ok] - planner.position, axis=-1)
        assert np.all((gaps == 0) | ((gaps >= 0.19 - 1e-6) & (gaps <= 0.21 + 1e-6)))
        gap = flight.closest_approach(planner.position, c.position[ok], peer.position,
                                      peer.position)
        assert np.all(gap > 0.05)  # the whole flight keeps clear, not only its end
        assert np.all(c.cost[ok] <= planner.budget_left)
        assert planner.map.known_free(planner.position, c.position[ok], 0.21).all()
        assert planner.map.known_free(planner.position, c.position[c.valid], 0.21).all()
        planner._command = None  # decide again from the same pose
    assert d.candidates.valid.sum() < d.candidates.valid.size  # some draws were rejected


def test_budget_exhaustion_hovers():
    planner = OnboardPlanner(spec_of(), 0, budget=0.01, team_size=3)
    sense_free(planner)
    d = planner.decide()
    assert d.hover and "budget exhausted" in d.reason


# ---------------------------------------------------------------------------------------
# Sensing, budget and radio bookkeeping


def test_sense_charges_distance_and_turns_and_records_history():
    spec = spec_of()
    planner = OnboardPlanner(spec, 0, budget=1.0, team_size=3)
    sense_free(planner, position=(0.5, 0.5, 0.5), heading=1, n_seen=3)
    d = planner.decide()
    planner.sense(d.position, d.heading, np.array([0, 27_000]), np.array([2, 0]), 5)
    expected = 1.0 - np.linalg.norm(d.position - np.float32([0.5, 0.5, 0.5])) \
        - (spec.turn_cost if d.heading != 1 else 0.0)
    assert planner.budget_left == pytest.approx(expected, abs=1e-6)
    assert planner.map.codes[0] == OCCUPIED  # index G^3 = 27000 means "not observed"
    assert len(planner.history_pose) == 2 and planner.step == 1
    np.testing.assert_allclose(planner.history_utility, np.float32([3, 5]) / 16)
    # A hover is not a move: the next sense records nothing and charges nothing.
    planner.decide(candidates=Candidates(planner.position[None], np.int32([planner.heading]),
                                         None, None))
    sense_free(planner, position=planner.position, heading=planner.heading)
    assert len(planner.history_pose) == 2 and planner.budget_left == pytest.approx(expected)


def test_messages_round_trip_float32_exactly_and_extend_histories():
    spec = spec_of()
    a, b = (OnboardPlanner(spec, i, budget=1.0, team_size=3) for i in range(2))
    rng = np.random.default_rng(0)
    for k in range(3):
        sense_free(a, position=rng.random(3).astype(np.float32), heading=k, n_seen=k)
        a._command = (a.position, a.position)  # pretend it moved: every sense is recorded
    message = messages.decode(a.message())
    np.testing.assert_array_equal(message.poses, np.asarray(a.history_pose))
    np.testing.assert_array_equal(message.utilities, np.asarray(a.history_utility))
    sense_free(b)
    b.receive(a.message(start=0))
    b.receive(a.message(start=2))  # overlapping: nothing duplicated
    assert len(b.peer_pose[0]) == 3 and b.receive(b.message()) is None  # own echo ignored
    np.testing.assert_array_equal(b.contacts[0], a.position)


def test_newer_protocol_and_malformed_messages_are_refused_without_side_effects():
    spec = spec_of()
    a, b = (OnboardPlanner(spec, i, budget=1.0, team_size=3) for i in range(2))
    sense_free(a)
    sense_free(b)
    record = json.loads(a.message())
    assert messages.PROTOCOL_VERSION == 5
    newer = dict(record, protocol=6)
    with pytest.raises(ProtocolVersionError, match="protocol 6; this runtime speaks protocol "
                                                   "5 only .update the runtime on this robot"):
        b.receive(json.dumps(newer).encode())
    # A message of protocol 3 (no seq, no tag) names the robot to update.
    older = {k: v for k, v in record.items() if k != "seq"} | {"protocol": 3}
    with pytest.raises(ProtocolVersionError, match="protocol 3; this runtime speaks protocol "
                                                   "5 only .update the runtime on robot 0"):
        b.receive(json.dumps(older).encode())
    bad = [b"\x00garbage", json.dumps(dict(record, poses=[[0.1, 0.2, float("nan"), 0.0]])),
           json.dumps(dict(record, sender=7)), json.dumps(dict(record, utilities=[])),
           json.dumps(dict(record, position=[2.0, 0.0, 0.0])), json.dumps({"type": "other"})]
    for data in bad:
        with pytest.raises(MessageError) as err:
            b.receive(data)
        assert "\n" not in str(err.value)
    assert b.contacts == {} and all(len(h) == 0 for h in b.peer_pose.values())


def test_nan_pose_and_bad_sensing_raise_one_clear_error_and_change_nothing():
    spec = spec_of()
    planner = OnboardPlanner(spec, 0, budget=1.0, team_size=3)
    with pytest.raises(PlannerStateError):
        planner.decide()
    sense_free(planner)
    d = planner.decide()
    snapshot = (planner.map.codes.copy(), len(planner.history_pose), planner.budget_left,
                planner.step, planner.utility_gp.count, planner._command)
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int8), 0)
    cases = [
        lambda: planner.sense(np.float32([0.5, np.nan, 0.5]), 1, *empty),
        lambda: planner.sense(np.float32([0.5, 1.5, 0.5]), 1, *empty),
        lambda: planner.sense(np.float32([0.5, 0.5]), 1, *empty),
        lambda: planner.sense(d.position, 7, *empty),
        lambda: planner.sense(d.position, 1, np.array([-3]), np.array([0]), 0),
        lambda: planner.sense(d.position, 1, np.array([3]), np.array([9]), 0),
        lambda: planner.sense(d.position, 1, np.zeros(0, np.int64), np.zeros(0, np.int8), -1),
        lambda: planner.decide(candidates=Candidates(np.float32([[np.nan, 0.5, 0.5]]),
                                                     np.int32([0]), None, None)),
        lambda: planner.decide(tie_break=np.zeros(3)),
    ]
    for case in cases:
        with pytest.raises(InvalidPoseError) as err:
            case()
        assert "\n" not in str(err.value)
    after = (planner.map.codes, len(planner.history_pose), planner.budget_left, planner.step,
             planner.utility_gp.count, planner._command)
    np.testing.assert_array_equal(after[0], snapshot[0])
    assert after[1:5] == snapshot[1:5] and after[5] is snapshot[5]


def test_policy_mode_needs_weights_and_ids_are_checked():
    with pytest.raises(ValueError, match="needs a policy"):
        OnboardPlanner(spec_of(), 0, budget=1.0, mode="policy")
    with pytest.raises(ValueError, match="robot_id"):
        OnboardPlanner(spec_of(), 3, budget=1.0, team_size=3)


def test_nbv_and_random_modes_choose_among_the_safe_candidates():
    """nbv takes the largest view gain per cost (spec.layout.nbv_score, by hand from the
    features it was given); random takes a safe candidate, and different seeds differ."""
    spec = spec_of()
    planner = OnboardPlanner(spec, 0, budget=0.5, team_size=3, facade_weight=2.0)
    sense_free(planner, position=(0.5, 0.5, 0.2))
    planner.map.grid[:, 20:, :] = UNKNOWN  # unknown space on one side: gains differ
    d = planner.decide(mode="nbv")
    f = d.features
    score = f[:, FEATURES.index("view_unknown_per_cost")] \
        + 2.0 * f[:, FEATURES.index("view_facade_per_cost")]
    assert d.reason == "nbv" and d.mask[d.index]
    assert score[d.index] == np.max(score[d.mask]) and np.ptp(score[d.mask]) > 0
    picks = set()
    for seed in range(6):
        robot = OnboardPlanner(spec, 0, budget=0.5, team_size=3, mode="random", seed=seed)
        sense_free(robot, position=(0.5, 0.5, 0.2))
        d = robot.decide()
        assert d.reason == "random" and d.mask[d.index]
        picks.add(tuple(d.pose))
    assert len(picks) > 1
    with pytest.raises(ValueError, match="allowed: greedy, nbv, random$"):
        planner.decide(mode="oracle")
