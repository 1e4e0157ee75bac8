"""Safe flight on the JAX side (jaxmripp.sim.geometry traversal, jaxmripp.sim.flight):
hand-worked geometry and brute-force references."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.sim import flight, geometry
from jaxmripp.sim.geometry import FREE, OCCUPIED, UNKNOWN
from test_runtime_flight import HAND_WORKED

G = 10
REACH = 0.5  # longest segment the tests traverse, as a fraction of the world


@functools.lru_cache(maxsize=None)
def _traverse():
    return jax.jit(jax.vmap(geometry.traverse, in_axes=(0, 0, None, None)),
                   static_argnums=(2, 3))


def visited(start, end) -> set:
    """Voxels of the segment start -> end, both given in voxel units."""
    s = np.asarray(start, np.float32)[None] / G
    e = np.asarray(end, np.float32)[None] / G
    voxels, _, _ = _traverse()(jnp.asarray(s), jnp.asarray(e), G, REACH)
    return set(map(tuple, np.asarray(voxels[0]).tolist()))


@pytest.mark.parametrize("start, end, expected", HAND_WORKED + [
    # Ending exactly on a plane, moving up: the end point belongs to the cell above it.
    ((0.5, 0.5, 0.5), (2.0, 0.5, 0.5), {(0, 0, 0), (1, 0, 0), (2, 0, 0)}),
    # Through a corner of three axes at once.
    ((0.5, 0.5, 0.5), (1.5, 1.5, 1.5), {(0, 0, 0), (1, 1, 1)}),
])
def test_traversal_hand_worked(start, end, expected):
    assert visited(start, end) == expected


def test_traversal_matches_dense_sampling():
    """Random segments of up to REACH: the voxel set equals the cells of 400,001 points
    along the segment (a reference with no shared code)."""
    rng = np.random.default_rng(3)
    starts = rng.uniform(0, G, (100, 3)).astype(np.float32)
    ends = np.clip(starts + rng.normal(size=(100, 3)) * 1.5, 0, G).astype(np.float32)
    voxels, _, _ = _traverse()(jnp.asarray(starts / G), jnp.asarray(ends / G), G, REACH)
    t = np.linspace(0.0, 1.0, 400_001)[:, None]
    flat = lambda v: np.unique((v[:, 0] * G + v[:, 1]) * G + v[:, 2])  # noqa: E731
    for s, e, got in zip(starts.astype(np.float64), ends.astype(np.float64), np.asarray(voxels)):
        reference = np.clip(np.floor(s + t * (e - s)), 0, G - 1).astype(int)
        np.testing.assert_array_equal(flat(got), flat(reference))
    # The flat form (what the map lookups read) lists the same voxels in the same order.
    indices, _, _ = jax.jit(jax.vmap(geometry.traverse, in_axes=(0, 0, None, None, None)),
                            static_argnums=(2, 3, 4))(
        jnp.asarray(starts / G), jnp.asarray(ends / G), G, REACH, True)
    v = np.asarray(voxels)
    np.testing.assert_array_equal(np.asarray(indices), (v[..., 0] * G + v[..., 1]) * G + v[..., 2])


def grid_with(cells, code, fill=FREE):
    grid = np.full((G, G, G), fill, np.int8)
    for c in cells:
        grid[c] = code
    return jnp.asarray(grid)


def test_known_free_and_occupied_tests_see_a_corner():
    """The corner-grazing flight touches (1, 1, 0): an obstacle or an unknown voxel there
    stops it, a neighbour off the line does not."""
    start = jnp.asarray([[0.05, 0.15, 0.05]]) * 1.0
    end = jnp.asarray([[0.15, 0.05, 0.05]])
    corner, aside = (1, 1, 0), (0, 0, 0)
    free = functools.partial(geometry.known_free, start[0], end, size=G, max_length=REACH)
    clear = functools.partial(geometry.not_mapped_occupied, start[0], end, size=G,
                              max_length=REACH)
    assert bool(free(occupancy=grid_with([aside], OCCUPIED))[0])
    assert not bool(free(occupancy=grid_with([corner], UNKNOWN))[0])
    assert bool(clear(occupancy=grid_with([corner], UNKNOWN))[0])
    assert not bool(clear(occupancy=grid_with([corner], OCCUPIED))[0])


def test_fly_until_stops_inside_the_last_free_cell():
    """A wall of cells x = 3: a flight from x = 0.5 to 5.5 stops midway between entering
    cell 2 (t = 0.3) and the wall (t = 0.5): x = 0.5 + 0.4 * 5 = 2.5."""
    wall = lambda v: v[..., 0] == 3  # noqa: E731
    start, end = jnp.asarray([0.05, 0.05, 0.05]), jnp.asarray([0.55, 0.05, 0.05])
    stop, hit, entry, voxel = geometry.fly_until(start, end, wall, G, REACH)
    assert bool(hit) and np.isclose(float(entry), 0.5)
    np.testing.assert_allclose(np.asarray(stop) * G, [2.5, 0.5, 0.5], atol=1e-5)
    assert tuple(np.asarray(voxel)) == (3, 0, 0)
    stop, hit, _, _ = geometry.fly_until(start, end, lambda v: v[..., 0] == 9, G, REACH)
    assert not bool(hit) and np.allclose(np.asarray(stop), np.asarray(end))


# ---------------------------------------------------------------------------------------
# Closest approach of two flights at one common speed


def approach(a0, a1, b0, b1):
    return float(flight.closest_approach(*(jnp.asarray(x, jnp.float32)
                                           for x in (a0, a1, b0, b1))))


def test_closest_approach_hand_worked():
    # Swapping places meet halfway.
    assert approach([0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 0, 0]) == pytest.approx(0, abs=1e-6)
    # Crossing at right angles, both at the crossing at t = 0.5.
    assert approach([0, .5, 0], [1, .5, 0], [.5, 0, 0], [.5, 1, 0]) == pytest.approx(0, abs=1e-6)
    # Same paths, but B starts 0.2 farther back: when A is at the crossing B is 0.2 short.
    # Gap |(t, .5) - (.5, t - .2)|, least at t = 0.6: sqrt(0.1^2 + 0.1^2).
    assert approach([0, .5, 0], [1, .5, 0], [.5, -.2, 0], [.5, .8, 0]) == pytest.approx(
        np.sqrt(0.02), abs=1e-6)
    # Flying through a hovering robot.
    assert approach([0, 0, 0], [1, 0, 0], [.4, 0, 0], [.4, 0, 0]) == pytest.approx(0, abs=1e-6)
    # Parallel flights 0.1 apart.
    assert approach([0, 0, 0], [1, 0, 0], [0, .1, 0], [1, .1, 0]) == pytest.approx(0.1, abs=1e-6)
    # A arrives early (length 0.2) and hovers at (0.2, 0.05); B passes it later.
    assert approach([0, .05, 0], [.2, .05, 0], [.6, 0, 0], [0, 0, 0]) == pytest.approx(
        0.05, abs=1e-6)


def test_closest_approach_matches_time_sampling():
    rng = np.random.default_rng(0)
    a0, a1, b0, b1 = (rng.uniform(0, 1, (100, 3)).astype(np.float32) for _ in range(4))
    got = np.asarray(flight.closest_approach(*map(jnp.asarray, (a0, a1, b0, b1))))
    t = np.linspace(0, 2, 20_001)[:, None, None]

    def at(p0, p1):
        length = np.linalg.norm(p1 - p0, axis=-1, keepdims=True)
        unit = (p1 - p0) / np.maximum(length, 1e-12)
        return p0 + unit * np.minimum(t, length)

    reference = np.linalg.norm(at(a0, a1) - at(b0, b1), axis=-1).min(axis=0)
    np.testing.assert_allclose(got, reference, atol=2e-4)


def test_the_higher_id_of_two_crossing_robots_holds():
    """0 and 1 cross at the same moment; 2 is far. Robot 1 holds for robot 0 (the lower id
    goes first), and nobody holds when they cannot hear each other or 0 hovers."""
    start = jnp.asarray([[0, .5, .5], [.5, 0, .5], [.9, .9, .9]], jnp.float32)
    target = jnp.asarray([[1, .5, .5], [.5, 1, .5], [.9, .9, .7]], jnp.float32)
    flying = jnp.ones(3, bool)
    heard = ~jnp.eye(3, dtype=bool)
    assert flight.holds(start, target, flying, heard, 0.05).tolist() == [False, True, False]
    deaf = flight.holds(start, target, flying, jnp.zeros((3, 3), bool), 0.05)
    assert not bool(deaf.any())
    hovering = flight.holds(start, target, flying.at[0].set(False), heard, 0.05)
    assert not bool(hovering.any())


def test_pads_are_apart_and_in_the_start_face():
    pads = np.asarray(flight.pads(jnp.zeros(3), 5, 0.06))
    np.testing.assert_allclose(pads, [[0, 0, 0], [.06, 0, 0], [.12, 0, 0], [0, 0, .06],
                                      [.06, 0, .06]], atol=1e-7)
    gaps = np.linalg.norm(pads[:, None] - pads[None], axis=-1) + np.eye(5)
    assert gaps.min() >= 0.06 - 1e-7


def test_a_segment_beyond_max_length_is_not_passed_silently():
    """Too long for its slots: the list is incomplete, so the flight is not known free and
    `fly_until` stops before the unchecked part."""
    start, end = jnp.asarray([0.05, 0.05, 0.05]), jnp.asarray([0.95, 0.95, 0.95])
    _, _, complete = geometry.traverse(start, end, G, 0.1)
    assert not bool(complete)
    free = jnp.full((G, G, G), FREE, jnp.int8)
    assert not bool(geometry.known_free(start, end[None], free, G, 0.1)[0])
    stop, hit, _, _ = geometry.fly_until(start, end, lambda v: v[..., 0] < 0, G, 0.1)
    assert bool(hit) and float(stop[0]) < 0.95


@pytest.mark.slow
def test_truncate_in_episodes():
    """The alternative rule in whole episodes (smoke worlds, random planner): with
    `truncate` flights stop where the map stops being known free -- blocked moves, never a
    collision."""
    from jaxmripp import config
    from jaxmripp.evaluation import baselines
    from jaxmripp.sim import episode
    from jaxmripp.sim.params import DynamicParams, EnvParams

    cfg = config.load("tests/smoke.yaml", ["safety.flight=truncate", "robots.count=3"])
    params, dyn = EnvParams.from_config(cfg), DynamicParams.from_config(cfg)
    planner = baselines.random_planner()
    run = jax.jit(jax.vmap(lambda k: episode.run(k, params, dyn, planner)))
    result = run(jax.random.split(jax.random.key(0), 12))
    assert int(result.obstacle_collisions.sum()) == 0
    assert int(result.blocked.sum()) > 0
    assert int(result.robot_collisions_in_range.sum()) == 0
