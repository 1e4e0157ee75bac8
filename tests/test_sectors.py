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
    # test_view's environment: the worker that runs both files (tests/conftest.py)
    # compiles its reset once.
    cfg = from_dict({"world": {"size": 20}, "candidates": {"positions": 6}})
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
    position = np.asarray(state.candidates.position, np.float64)
    azimuth = np.degrees(np.arctan2(position[..., 1], position[..., 0]))  # pad 0 at (0, 0)
    gain = np.asarray(obs.features)[..., FEATURES.index("view_unknown")] > 0
    mask = np.asarray(obs.mask)
    restricted = 0
    for robot, (lo, hi) in enumerate([(0, 30), (30, 60), (60, 90)]):
        mine = (azimuth >= lo) & ((azimuth < hi) | (hi == 90))
        useful = mask[robot] & mine[robot] & gain[robot]
        expected = useful if useful.any() else mask[robot]
        np.testing.assert_array_equal(offered[robot], expected)
        restricted += int(useful.any() and useful.sum() < mask[robot].sum())
    assert restricted > 0
    # Every planner of a sweep with eval.sectors (here random) chooses among those only.
    memory = jnp.zeros((3, 1))
    for planner, inside in [(random_planner(), False), (deployed(random_planner(), True), True)]:
        act = jax.jit(planner.act)
        chosen = np.stack([np.asarray(act(jax.random.PRNGKey(10 + k), memory, obs, state,
                                          dyn)[1]) for k in range(8)])
        assert offered[np.arange(3), chosen].all() == inside
