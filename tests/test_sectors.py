"""The sector rule (jaxmripp.spec.sectors) on hand-worked geometry, on both array sides,
and applied to a trained policy's masks."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.config import from_dict
from jaxmripp.evaluation.baselines import random_planner
from jaxmripp.evaluation.planners import deployed
from jaxmripp.sim.observation import in_sectors
from jaxmripp.sim import env
from jaxmripp.sim.params import DynamicParams, EnvParams
from jaxmripp.spec import sectors
from jaxmripp.spec.layout import FEATURES


def _at_azimuths(degrees, start=(0.0, 0.0, 0.0), radius=0.3):
    a = np.radians(np.asarray(degrees, np.float64))
    s = np.asarray(start)
    return np.stack([s[0] + radius * np.cos(a), s[1] + radius * np.sin(a),
                     np.full_like(a, 0.2)], axis=-1).astype(np.float32)


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
def test_a_corner_pad_splits_the_quarter_turn_evenly(xp):
    # From the corner (0, 0) the world spans azimuths 0-90 degrees: 30 degrees per robot.
    positions = xp.asarray(_at_azimuths([5, 29, 31, 59, 61, 89, 90]))
    start = xp.asarray([0.0, 0.0, 0.0], xp.float32)
    owners = [[bool(v) for v in np.asarray(sectors.own_sector(positions, start, robot, 3, xp=xp))]
              for robot in range(3)]
    assert owners[0] == [True, True, False, False, False, False, False]
    assert owners[1] == [False, False, True, True, False, False, False]
    assert owners[2] == [False, False, False, False, True, True, True]  # the last is closed


def test_a_pad_mid_edge_spans_a_half_turn():
    # From (0.5, 0) the corners lie at 0, 63.4, 116.6 and 180 degrees: two robots split
    # at 90.
    start = np.asarray([0.5, 0.0, 0.0], np.float32)
    positions = _at_azimuths([10, 80, 100, 170], start=start, radius=0.2)
    np.testing.assert_array_equal(sectors.own_sector(positions, start, 0, 2),
                                  [True, True, False, False])
    np.testing.assert_array_equal(sectors.own_sector(positions, start, 1, 2),
                                  [False, False, True, True])
    assert math.isclose(math.degrees(math.atan2(1.0, -0.5)), 116.565, abs_tol=1e-3)


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
def test_a_pad_on_the_far_edge_splits_the_world_into_left_and_right(xp):
    # From (0.5, 1) the world lies at azimuths -180 to 0 degrees, across the +-180 cut of
    # atan2: two robots split it at x = 0.5, robot 0 on the x < 0.5 side.
    start = xp.asarray([0.5, 1.0, 0.0], xp.float32)
    positions = xp.asarray([[0.2, 0.5, 0.2], [0.05, 0.95, 0.2], [0.8, 0.5, 0.2],
                            [0.95, 0.95, 0.2]], xp.float32)
    for robot, expected in ((0, [True, True, False, False]), (1, [False, False, True, True])):
        np.testing.assert_array_equal(
            np.asarray(sectors.own_sector(positions, start, robot, 2, xp=xp)), expected)


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
def test_an_equal_area_split_of_a_corner_pad_cuts_at_two_thirds_of_the_edges(xp):
    # From (0, 0), a third of the square is the triangle (0, 0), (1, 0), (1, 2/3): the
    # cuts lie at atan(2/3) = 33.69 and 56.31 degrees, not at 30 and 60.
    positions = xp.asarray(_at_azimuths([5, 33.6, 33.8, 56.2, 56.4, 90]))
    start = xp.asarray([0.0, 0.0, 0.0], xp.float32)
    owners = [[bool(v) for v in np.asarray(sectors.own_sector(positions, start, robot, 3, xp=xp,
                                                              equal_area=True))]
              for robot in range(3)]
    assert owners == [[True, True, False, False, False, False],
                      [False, False, True, True, False, False],
                      [False, False, False, False, True, True]]


@pytest.mark.parametrize("start, team", [((0.0, 0.0), 3), ((0.5, 0.0), 4), ((0.3, 1.0), 5),
                                         ((1.0, 0.7), 2), ((1.0, 1.0), 7)])
def test_equal_area_sectors_hold_equal_shares_of_random_ground(start, team):
    """Counted on uniform random ground points: every sector holds 1/N of them (the
    azimuth split from a corner gives the diagonal sectors more)."""
    ground = np.random.default_rng(team).random((40_000, 2))
    points = np.concatenate([ground, np.full((len(ground), 1), 0.2)], axis=1)
    pad = np.asarray([*start, 0.0], np.float32)
    shares = [sectors.own_sector(points, pad, robot, team, equal_area=True).mean()
              for robot in range(team)]
    np.testing.assert_allclose(shares, 1 / team, atol=0.01)
    assert sum(shares) == pytest.approx(1.0)
    by_angle = [sectors.own_sector(points, pad, robot, team).mean() for robot in range(team)]
    assert max(by_angle) - min(by_angle) > 0.05


@pytest.mark.parametrize("team", [1, 2, 3, 7, 16, 64])
def test_pad_rank_orders_the_pads_farthest_column_first(team):
    side = math.ceil(math.sqrt(team))
    robots = np.arange(team)
    # Brute force: sort by (column descending, index).
    order = sorted(robots, key=lambda i: (-(i % side), i))
    expected = np.empty(team, int)
    expected[order] = np.arange(team)
    np.testing.assert_array_equal(sectors.pad_rank(robots, team), expected)
    np.testing.assert_array_equal(np.asarray(sectors.pad_rank(jnp.arange(team), team, jnp)),
                                  expected)
    assert [int(sectors.pad_rank(i, team)) for i in robots] == list(expected)


@pytest.mark.parametrize("xp", [np, jnp], ids=["numpy", "jax"])
@pytest.mark.parametrize("equal_area", [False, True], ids=["angle", "area"])
def test_shared_sectors_go_to_the_robots_by_pad_rank(xp, equal_area):
    # Six robots on a 3-wide pad grid from the corner (0, 0): columns 2, 1, 0 hold robots
    # (2, 5), (1, 4), (0, 3), so with three sectors robots 2 and 5 share the first
    # (beside +x), 1 and 4 the second, 0 and 3 the third. Cuts at 30 / 60 degrees by
    # angle, atan(2/3) = 33.69 / 56.31 by area.
    degrees = [5, 32, 35, 55, 58, 89]
    positions = xp.asarray(_at_azimuths(degrees))
    start = xp.asarray([0.0, 0.0, 0.0], xp.float32)
    cuts = [33.69, 56.31] if equal_area else [30, 60]
    sector_of_point = np.searchsorted(cuts, degrees)
    for robot, sector in enumerate([2, 1, 0, 2, 1, 0]):
        owned = sectors.own_sector(positions, start, robot, 6, xp=xp, equal_area=equal_area,
                                   count=3)
        np.testing.assert_array_equal(np.asarray(owned), sector_of_point == sector)
    # One sector for the whole team: everyone owns everything.
    whole = [np.asarray(sectors.own_sector(positions, start, robot, 6, xp=xp, count=1))
             for robot in range(6)]
    assert np.all(whole)


def test_the_mask_keeps_the_own_sector_while_it_has_views_there():
    gain = FEATURES.index("view_unknown")
    features = np.zeros((2, 4, len(FEATURES)), np.float32)
    features[0, :, gain] = [0.0, 0.2, 0.3, 0.4]  # robot 0: its sector holds candidates 0-1
    features[1, :, gain] = [0.5, 0.0, 0.3, 0.0]  # robot 1: its sector (0-1) has no view left
    mask = np.asarray([[True, True, True, False], [True, True, True, True]])
    own = np.asarray([[True, True, False, False], [False, True, False, True]])
    kept = sectors.sector_mask(mask, features, own)
    np.testing.assert_array_equal(kept, [[False, True, False, False], mask[1]])
    np.testing.assert_array_equal(sectors.sector_mask(jnp.asarray(mask), jnp.asarray(features),
                                                      jnp.asarray(own)), kept)


def test_robots_in_sectors_are_offered_only_their_own_views():
    """After a few steps of a 3-robot team, each robot's offered candidates are those of
    its sector with view gain (checked against NumPy azimuths), or its whole mask, and a
    planner deployed with sectors picks among them."""
    cfg = from_dict({"world": {"size": 20}, "candidates": {"positions": 8},
                     "safety": {"takeoff_scan": True}})
    params, dyn = EnvParams.from_config(cfg), DynamicParams.from_config(cfg)
    obs, state = jax.jit(env.reset, static_argnums=1)(jax.random.PRNGKey(8), params, dyn)
    step = jax.jit(env.step, static_argnums=3)
    for t in range(3):  # the last feasible candidate: flights away from the pads
        last = obs.mask.shape[-1] - 1 - jnp.argmax(obs.mask[:, ::-1], axis=-1)
        obs, state, *_ = step(jax.random.PRNGKey(t), state, last, params, dyn)
    offered = np.asarray(jax.jit(in_sectors)(obs, state, dyn).mask)
    # A radio that reaches across the world (rho >= the diagonal, sqrt 3) turns it off.
    for rho, on in [(1.73, True), (1.74, False), (np.inf, False)]:
        far = jax.jit(in_sectors)(obs, state, dyn.replace(radio_range=jnp.float32(rho))).mask
        np.testing.assert_array_equal(np.asarray(far), offered if on else np.asarray(obs.mask))
    # With radio.sector_split = area (dyn.sector_area, traced: the same compilation) the
    # cuts move from 30 and 60 degrees to 33.69 and 56.31 (the corner pad's thirds).
    by_area = np.asarray(jax.jit(in_sectors)(obs, state, dyn.with_values(sector_area=1.0)).mask)
    assert np.any(by_area != offered)
    # With radio.sector_count = 2 (dyn.sector_count, traced too) the pads' columns rank
    # robot 1 (x = spacing) first, then robots 0 and 2 (x = 0): robots 1 and 0 share
    # 0-45 degrees, robot 2 owns 45-90.
    by_count = np.asarray(jax.jit(in_sectors)(obs, state, dyn.with_values(sector_count=2)).mask)
    position = np.asarray(state.candidates.position, np.float64)
    azimuth = np.degrees(np.arctan2(position[..., 1], position[..., 0]))  # pad 0 at (0, 0)
    gain = np.asarray(obs.features)[..., FEATURES.index("view_unknown")] > 0
    mask = np.asarray(obs.mask)
    thirds = [math.degrees(math.atan(2 / 3)), math.degrees(math.atan(3 / 2))]
    for got, spans in [(offered, [(0, 30), (30, 60), (60, 90)]),
                       (by_area, [(0, thirds[0]), (thirds[0], thirds[1]), (thirds[1], 90)]),
                       (by_count, [(0, 45), (0, 45), (45, 90)])]:
        restricted = 0
        for robot, (lo, hi) in enumerate(spans):
            mine = (azimuth >= lo) & ((azimuth < hi) | (hi == 90))
            useful = mask[robot] & mine[robot] & gain[robot]
            expected = useful if useful.any() else mask[robot]
            np.testing.assert_array_equal(got[robot], expected)
            restricted += int(useful.any() and useful.sum() < mask[robot].sum())
        assert restricted > 0
    # Every planner of a sweep with eval.sectors (here random) chooses among those only.
    memory = jnp.zeros((3, 1))
    for planner, inside in [(random_planner(), False), (deployed(random_planner(), True), True)]:
        act = jax.jit(planner.act)
        chosen = np.stack([np.asarray(act(jax.random.PRNGKey(10 + k), memory, obs, state,
                                          dyn)[1]) for k in range(8)])
        assert offered[np.arange(3), chosen].all() == inside
