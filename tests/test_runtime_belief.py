"""The target belief onboard (`jaxmripp.runtime.belief`, rule `jaxmripp.spec.belief`): its
buildings, counts, posterior rates, facade rates and rate-weighted gain against the JAX
implementation (`jaxmripp.sim.belief`, `jaxmripp.sim.view`) and the reference written
from the rule's text (tests/test_belief.py) on randomised maps; the window bits of the map
deltas (protocol 5: round trip, bits learned late, malformed fields refused with nothing
changed, the team key). The whole episodes with an exported belief policy are in
tests/test_runtime_belief_episode.py."""

from __future__ import annotations

import base64
import copy
import dataclasses
import functools
import json
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config as cfgmod, export
from jaxmripp.runtime import (InvalidPoseError, MessageError, OnboardPlanner, belief, messages,
                              team_key, validation, view)
from jaxmripp.runtime.mapping import OccupancyMap
from jaxmripp.sim import belief as sim_belief
from jaxmripp.spec import belief as spec
from jaxmripp.spec.grid import FREE, OCCUPIED, UNKNOWN
from jaxmripp.spec.layout import BELIEF_FEATURES, FEATURES
from test_belief import (SENSOR, WORLD, _scene, gain, reference_labels, reference_rates,
                         team_rates)
from test_runtime import REPO
from test_runtime_auth import fingerprint

PRIOR = sim_belief.prior(WORLD)
F = WORLD.footprint


@functools.partial(jax.jit, static_argnums=3)
def sim_column_rates(world, team_map, top, strength):
    """(N, G, G) float32 each robot's column rates rho by `jaxmripp.sim.belief`'s steps
    (`robot_rates` short of the quantisation and the facade maximum)."""
    n, size = top.shape[0], WORLD.size
    cells = sim_belief.building_boxes(world.height, WORLD)
    flat = cells.reshape(-1)
    windows = sim_belief.known_windows(team_map, world.target_voxel, world.target_valid, n)
    seen = sim_belief.known_facade(team_map, flat, n)

    def one(top_i, seen_i, windows_i):
        known = (flat < size * size) & (top_i.reshape(-1)[jnp.minimum(flat, size * size - 1)]
                                         > 0)
        labels = sim_belief.box_labels(known.reshape(-1, F * F), cells, F, size).reshape(-1)
        found = sim_belief._sums(sim_belief._window_labels(labels, flat, world.target_voxel,
                                                           size), windows_i, size)
        rho = spec.relative_rate(found, sim_belief._sums(labels, seen_i, size), strength,
                                 PRIOR, jnp)
        return sim_belief._rate_grid(rho, labels, flat, size)

    return jax.vmap(one)(top, seen, windows)


def onboard_map(grid, top, world) -> OccupancyMap:
    """A runtime map holding a robot's map and tops, with the windows a classifier that
    is always right reported wherever the map holds a window's voxel."""
    size = grid.shape[0]
    occupancy = OccupancyMap(size)
    occupancy.codes[:] = grid.reshape(-1)
    occupancy.top[:] = top
    voxel, valid = np.asarray(world.target_voxel), np.asarray(world.target_valid)
    flat = (voxel[:, 0] * size + voxel[:, 1]) * size + voxel[:, 2]
    occupancy.mark_windows(flat[valid & (occupancy.codes[flat] != UNKNOWN)])
    return occupancy


@pytest.fixture(scope="module")
def scenes():
    """Three generated cities, each with two robots' maps from six random casts."""
    return [_scene(seed) for seed in range(3)]


@pytest.mark.parametrize("strength", [1.0, 3.0])
def test_posterior_rates_equal_the_jax_belief_and_the_written_rule(scenes, strength):
    checked = 0
    for state, grids, tops in scenes:
        sim_rho = np.asarray(sim_column_rates(state.world, state.team_map, state.building_top,
                                              strength))
        for i, (grid, top) in enumerate(zip(grids, tops)):
            ours = belief.belief(onboard_map(grid, top, state.world), strength, PRIOR)
            np.testing.assert_array_equal(ours.labels, reference_labels(top))
            # Counts by building, from the rule's text: OCCUPIED voxels and known windows.
            for label, seen, found in zip(ours.buildings, ours.seen, ours.found):
                columns = ours.labels == label
                assert seen == int((grid[columns] == OCCUPIED).sum())
                voxel = np.asarray(state.world.target_voxel)
                assert found == sum(
                    1 for (x, y, z), v in zip(voxel, np.asarray(state.world.target_valid))
                    if v and columns[x, y] and grid[x, y, z] != UNKNOWN)
            np.testing.assert_allclose(ours.column_rates(), sim_rho[i], rtol=1e-6, atol=0)
            assert len(ours.buildings) >= 2 and np.ptp(ours.rho) > 0
            checked += int(ours.found.sum() > 0)
    assert checked >= 3  # buildings with known windows, on most maps


@pytest.mark.parametrize("facade", ["nearby", "around", "column"])
def test_facade_rates_and_weighted_gain_equal_the_jax_ones(scenes, facade):
    sensor = dataclasses.replace(SENSOR, gain_facade=facade)
    model = view.GainModel(sensor.fov_deg, sensor.range, sensor.gain_occlusion, facade)
    rng = np.random.default_rng(3)
    weighted = 0
    for state, grids, tops in scenes:
        want = np.asarray(team_rates(state.world, state.team_map, state.building_top, 3.0,
                                     sensor))
        for i, (grid, top) in enumerate(zip(grids, tops)):
            occupancy = onboard_map(grid, top, state.world)
            q = belief.facade_rates(occupancy, 3.0, PRIOR, facade)
            # float32 on both sides; one unit where a fused multiply-add rounds otherwise.
            assert np.abs(q - want[i]).max() <= 1 and np.mean(q == want[i]) > 0.99
            assert np.abs(q - reference_rates(
                grid, top, np.asarray(state.world.target_voxel),
                np.asarray(state.world.target_valid), 3.0, PRIOR, facade)).max() <= 1
            # Poses near buildings the robot knows, which see rated facade.
            columns = np.argwhere(top > 0)[rng.integers(0, (top > 0).sum(), 8)]
            position = np.clip(np.c_[(columns + 0.5) / WORLD.size, np.zeros(8)]
                               + rng.uniform([-0.15, -0.15, 0.1], [0.15, 0.15, 0.5], (8, 3)),
                               0.02, 0.98).astype(np.float32)
            jax_gains = [np.asarray(g).reshape(-1) for g in
                         gain(grid, top, position, sensor, WORLD.size, jnp.asarray(q))]
            ours = view.view_gain(occupancy.codes, occupancy.top, np.repeat(position, 4, 0),
                                  np.tile(np.arange(4), 8), model, WORLD.size, rates=q)
            for got, expected in zip(ours, jax_gains):
                np.testing.assert_array_equal(got, expected)
            weighted += int(np.any(ours[2] != ours[1]))
            # Every rate at the prior: view_windows is view_facade, bit for bit.
            prior = view.view_gain(occupancy.codes, occupancy.top, np.repeat(position, 4, 0),
                                   np.tile(np.arange(4), 8), model, WORLD.size,
                                   rates=np.full_like(q, spec.RATE_SCALE))
            np.testing.assert_array_equal(prior[2], ours[1])
    assert weighted >= 4  # the rates weigh the facade on most maps


def test_labels_join_two_walls_once_a_column_links_them():
    top = np.zeros((10, 10), np.int8)
    top[2, 2:5] = top[4, 2:5] = 5
    assert set(np.unique(belief.building_labels(top))) == {22, 42, 100}
    top[3, 4] = 5
    assert set(np.unique(belief.building_labels(top))) == {22, 100}
    spiral = np.zeros((9, 9), np.int8)  # one long 8-connected path: many spreading rounds
    spiral[0, :] = spiral[:, 8] = spiral[8, :] = spiral[2:, 0] = spiral[2, :7] = 1
    spiral[2:7, 6] = spiral[6, 2:7] = 1
    np.testing.assert_array_equal(belief.building_labels(spiral), reference_labels(spiral))


# ---------------------------------------------------------------------------------------
# Windows in sense and in the map deltas

CFG = cfgmod.load(REPO / "tests/smoke.yaml", ["world.size=30", "robots.count=3",
                                                 "policy.belief_features=true"])
SPEC = export.runtime_spec(CFG)
G = SPEC.size


def test_the_export_header_carries_the_belief_and_its_prior():
    assert SPEC.belief_features and SPEC.belief_strength == CFG.policy.belief_strength
    assert SPEC.belief_prior == sim_belief.prior(CFG.world)
    assert SPEC.features == FEATURES + BELIEF_FEATURES
    assert not export.runtime_spec(cfgmod.load(REPO / "tests/smoke.yaml")).belief_features


def building_voxels(x, y, height):
    """Flat indices of a column's voxels 0 .. height - 1."""
    return (x * G + y) * G + np.arange(height)


def planners(key=None, spec=SPEC):
    """Robots 0 and 1: robot 0 saw two walls' columns (x, y) = (10, 10) and (10, 11) and
    the air beside them, robot 1 only free air; both heard each other."""
    team = [OnboardPlanner(spec, i, budget=2.0, team_size=3, team_key=key) for i in range(2)]
    wall = np.concatenate([building_voxels(10, 10, 6), building_voxels(10, 11, 6)])
    air = building_voxels(12, 10, 8)
    a, b = team
    a.sense(np.float32([0.42, 0.35, 0.2]), 1, np.concatenate([wall, air]),
            np.r_[np.full(wall.size, OCCUPIED), np.full(air.size, FREE)].astype(np.int8), 2,
            windows=wall[[2, 8]])
    b.sense(np.float32([0.45, 0.6, 0.2]), 1, air, np.full(air.size, FREE, np.int8), 0)
    a.receive(b.message())
    b.receive(a.message())
    return team, wall


def test_window_bits_travel_with_the_map_and_late_ones_travel_again():
    (a, b), wall = planners()
    data = a.map_message()
    b.map_message()
    b.receive_map(data)
    np.testing.assert_array_equal(np.flatnonzero(b.map.window), np.sort(wall[[2, 8]]))
    # The belief b reads now: one building of 12 facade voxels with two windows.
    ours = belief.belief(b.map, SPEC.belief_strength, SPEC.belief_prior)
    assert ours.seen.tolist() == [12] and ours.found.tolist() == [2]
    assert ours.rho[0] == spec.relative_rate(2, 12, SPEC.belief_strength, SPEC.belief_prior)
    # Next round robot 0's classifier names a voxel it mapped before: it goes out again,
    # alone, with its bit.
    a.sense(a.position, 1, wall[:1], np.int8([OCCUPIED]), 1, windows=wall[:1])
    b.sense(b.position, 1, [], np.zeros(0, np.int8), 0)
    a.receive(b.message())
    b.receive(a.message())
    delta = messages.decode_map(a.map_message(), G, windows=True).delta_for(1)
    assert delta.voxels.tolist() == [wall[0]] and delta.windows.tolist() == [True]
    b.map_message()
    b.receive_map(messages.encode_map(messages.MapMessage(0, G, (delta,))))
    assert b.map.window[wall[0]] and b.map.window.sum() == 3


def test_window_bits_round_trip_and_cost_a_few_bytes():
    rng = np.random.default_rng(4)
    voxels = np.sort(rng.choice(G ** 3, 500, replace=False))
    occupied = rng.random(500) < 0.4
    windows = occupied & (rng.random(500) < 0.2)
    delta = messages.MapDelta(2, voxels, occupied, windows)
    plain = messages.encode_map(messages.MapMessage(1, G, (dataclasses.replace(
        delta, windows=None),)))
    data = messages.encode_map(messages.MapMessage(1, G, (delta,)))
    back = messages.decode_map(data, G, windows=True).deltas[0]
    np.testing.assert_array_equal(back.windows, windows)
    np.testing.assert_array_equal(back.occupied, occupied)
    # One bit per OCCUPIED voxel, compressed: tens of bytes beside the masks.
    assert 0 < len(data) - len(plain) < occupied.sum() // 8 + 40
    assert messages.decode_map(plain, G).deltas[0].windows is None


def malformed(record, change):
    entry = dict(record["deltas"][0], **change)
    if change.get("windows") is None:
        entry.pop("windows")
    return json.dumps(dict(record, deltas=[entry]))


def test_malformed_window_bits_are_refused_and_change_nothing():
    (a, b), _ = planners()
    record = json.loads(a.map_message())
    b.map_message()
    entry = record["deltas"][0]
    bits = int(np.unpackbits(np.frombuffer(zlib.decompress(base64.b64decode(
        entry["occupied"])), np.uint8)).sum())
    assert bits == 12 and bits % 8  # padding bits exist
    packed = lambda raw: base64.b64encode(zlib.compress(raw)).decode()  # noqa: E731
    bad = {
        "missing": {"windows": None},
        "not base64": {"windows": "@@"},
        "not a string": {"windows": [1, 0]},
        "one byte short": {"windows": packed(b"\x00")},
        "one byte long": {"windows": packed(b"\x00\x00\x00")},
        "padding set": {"windows": packed(b"\x00\x0f")},
        "not zlib": {"windows": base64.b64encode(b"\x00\x00").decode()},
    }
    before = fingerprint(b)
    for name, change in bad.items():
        with pytest.raises(MessageError, match="windows|window bits") as err:
            b.receive_map(malformed(record, change))
        assert "\n" not in str(err.value), name
        assert fingerprint(b) == before, name
    assert b.rejected_messages["malformed"] == len(bad)
    # A robot without the belief refuses window bits: a team flies one export.
    plain = dataclasses.replace(SPEC, belief_features=False)
    (c, d), _ = planners(spec=plain)
    d.map_message()
    with pytest.raises(MessageError, match="holds window bits; this robot's export has no"):
        d.receive_map(json.dumps(record))
    b.receive_map(json.dumps(record))  # the message itself is fine
    assert b.map.window.sum() == 2


def test_signed_window_bits_are_taken_and_altered_ones_refused():
    key = team_key(5)
    (a, b), wall = planners(key)
    data = a.map_message()
    b.map_message()
    tampered = copy.deepcopy(b)
    record = data.decode()
    windows = json.loads(record)["deltas"][0]["windows"]  # the tag is one more member
    forged = record.replace(windows, base64.b64encode(zlib.compress(b"\x40\x00")).decode())
    assert forged != record
    with pytest.raises(MessageError) as err:
        tampered.receive_map(forged.encode())
    assert err.value.reason == "forged" and not tampered.map.window.any()
    b.receive_map(data)
    np.testing.assert_array_equal(np.flatnonzero(b.map.window), np.sort(wall[[2, 8]]))


def test_sense_refuses_windows_that_are_not_occupied_and_changes_nothing():
    (a, _), wall = planners()
    before = fingerprint(a)
    free = building_voxels(12, 10, 1)
    for windows, match in [(free, "not mapped occupied"), ([G ** 3], "flat voxel indices"),
                           (np.float32([3.0]), "flat voxel indices"),
                           (np.array([[10, 10, G]]), "window coordinates")]:
        with pytest.raises(InvalidPoseError, match=match):
            a.sense(a.position, 1, wall[:1], np.int8([OCCUPIED]), 0, windows=windows)
        assert fingerprint(a) == before
    # A voxel this call writes FREE over an OCCUPIED one is no window any more either.
    with pytest.raises(InvalidPoseError, match="not mapped occupied"):
        a.sense(a.position, 1, wall[:1], np.int8([FREE]), 0, windows=wall[:1])
    # Coordinates are taken too, and voxels the map already holds OCCUPIED.
    a.sense(a.position, 1, [], np.zeros(0, np.int8), 0, windows=np.array([[10, 11, 3]]))
    assert a.map.window[(10 * G + 11) * G + 3]


def test_depth_sightings_the_map_left_unmapped_are_dropped():
    """`sense_depth`'s windows: only those OCCUPIED once its voxels are written (the last
    write of a voxel wins) are kept; `sense` refuses the others."""
    known = np.full(G ** 3, UNKNOWN, np.int8)
    known[7] = OCCUPIED
    flat, codes = np.array([5, 9, 5, 12]), np.int8([OCCUPIED, FREE, FREE, OCCUPIED])
    sightings = np.array([5, 7, 9, 11, 12])
    kept = validation.windows(sightings, flat, codes, known, G, drop=True)
    assert kept.tolist() == [7, 12]
    with pytest.raises(InvalidPoseError, match="not mapped occupied"):
        validation.windows(sightings, flat, codes, known, G)
