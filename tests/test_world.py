"""City generation: determinism, layouts that never overlap, windows where they belong."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from jaxmripp.sim import geometry, world
from jaxmripp.config import WorldConfig

_generate = jax.jit(world.generate, static_argnums=1)


@functools.lru_cache(maxsize=None)
def city(seed: int, **overrides) -> tuple[WorldConfig, world.World]:
    """Generates once per (seed, config); the World holds NumPy arrays for the checks."""
    cfg = WorldConfig(**overrides)
    w = _generate(jax.random.PRNGKey(seed), cfg)
    return cfg, jax.tree.map(np.asarray, w)


def footprints(height: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Boxes (lo, hi inclusive) of the building blobs; 8-connected so touching ones merge."""
    labels, count = ndimage.label(height > 0, structure=np.ones((3, 3)))
    boxes = []
    for sl in ndimage.find_objects(labels):
        lo = np.array([s.start for s in sl])
        boxes.append((lo, np.array([s.stop - 1 for s in sl])))
    return boxes


def assert_layout(cfg: WorldConfig, height: np.ndarray):
    boxes = footprints(height)
    assert len(boxes) == cfg.n_buildings
    for lo, hi in boxes:
        assert np.all(hi - lo + 1 == cfg.footprint), "footprints merged or clipped"
        assert np.all(lo >= cfg.clearance) and np.all(hi < cfg.size - cfg.clearance)
    for i, (lo_i, hi_i) in enumerate(boxes):
        for lo_j, hi_j in boxes[i + 1:]:
            gap = np.maximum(lo_j - hi_i - 1, lo_i - hi_j - 1)  # free voxels between, per axis
            assert gap.max() >= cfg.clearance
    assert height[0, 0] == 0


def test_deterministic_per_key_and_keys_differ():
    for layout in ("grid", "random"):
        cfg = WorldConfig(layout=layout)
        a = _generate(jax.random.PRNGKey(7), cfg)
        b = _generate(jax.random.PRNGKey(7), cfg)
        c = _generate(jax.random.PRNGKey(8), cfg)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_array_equal(x, y)
        assert not np.array_equal(a.height, c.height)
        assert not np.array_equal(a.target_voxel, c.target_voxel)


@pytest.mark.parametrize("layout", ["grid", "random"])
@pytest.mark.parametrize("clearance", [1, 2])
def test_footprints_never_overlap_and_keep_clearance(layout, clearance):
    for seed in range(3):
        cfg, w = city(seed, layout=layout, clearance=clearance)
        assert_layout(cfg, w.height)


def test_grid_layout_is_a_regular_lattice():
    cfg, w = city(0, layout="grid")
    lows = np.array([lo for lo, _ in footprints(w.height)])
    xs, ys = np.unique(lows[:, 0]), np.unique(lows[:, 1])
    assert len(xs) == len(ys) == 5  # 25 buildings at G = 50: 5 x 5
    assert np.ptp(np.diff(xs)) <= 1 and np.ptp(np.diff(ys)) <= 1  # evenly spread


def test_heights_in_range():
    cfg, w = city(1, layout="random")
    heights = w.height[w.height > 0]
    lo, hi = cfg.height_range
    assert heights.min() >= max(1, int(lo * cfg.size)) and heights.max() <= hi * cfg.size


def check_windows(cfg: WorldConfig, w):
    valid = w.target_valid
    n = int(valid.sum())
    assert cfg.target_min <= n <= cfg.target_capacity
    assert valid[:n].all() and not valid[n:].any(), "valid windows come first"
    v = w.target_voxel[valid]
    assert len(np.unique(v, axis=0)) == n, "windows are distinct"
    assert np.all(v[:, 2] < w.height[v[:, 0], v[:, 1]]), "windows are building voxels"
    assert np.all(np.asarray(world.occupied(w, jnp.asarray(v))))
    if cfg.target_placement == "facade":
        padded = np.pad(w.height, 1)  # out of the grid is free
        x, y, z = v[:, 0] + 1, v[:, 1] + 1, v[:, 2]
        neighbours = np.stack([padded[x - 1, y], padded[x + 1, y],
                               padded[x, y - 1], padded[x, y + 1]])
        assert np.all(np.any(neighbours <= z, axis=0)), "every facade window faces free space"


@pytest.mark.parametrize("size", [50, 75, 100, 125])
def test_windows_at_every_world_size(size):
    cfg, w = city(size, size=size, layout="random", targets=(200, 250))
    assert w.height.shape == (size, size) and w.target_voxel.shape == (cfg.target_capacity, 3)
    assert_layout(cfg, w.height)
    check_windows(cfg, w)


def test_window_count_varies_in_range():
    cfg = WorldConfig(targets=(200, 250))
    keys = jax.random.split(jax.random.PRNGKey(0), 16)
    worlds = jax.jit(jax.vmap(lambda k: world.generate(k, cfg)))(keys)
    counts = np.asarray(worlds.n_targets)
    assert counts.min() >= 200 and counts.max() <= 250 and len(np.unique(counts)) > 4


def test_windows_split_unevenly_across_buildings():
    cfg, w = city(3, layout="grid")
    v = w.target_voxel[w.target_valid]
    labels, _ = ndimage.label(w.height > 0, structure=np.ones((3, 3)))
    per_building = np.bincount(labels[v[:, 0], v[:, 1]], minlength=cfg.n_buildings + 1)[1:]
    assert per_building.sum() == len(v) and per_building.std() > 2


def test_footprint_placement_windows_inside_footprints():
    cfg, w = city(4, layout="random", target_placement="footprint")
    check_windows(cfg, w)
    v = w.target_voxel[w.target_valid]
    # Some windows sit in the middle column of a 3 x 3 footprint, unlike facades.
    interior = np.all(np.stack([w.height[v[:, 0] + dx, v[:, 1] + dy] > 0
                                for dx in (-1, 1) for dy in (-1, 1)]), axis=0)
    assert interior.any()


def test_occupied_and_truth_agree():
    cfg, w = city(5, layout="random")
    truth = np.asarray(world.truth_occupancy(w, cfg.size))
    assert truth.dtype == np.int8 and set(np.unique(truth)) <= {geometry.FREE, geometry.OCCUPIED}
    voxels = np.stack(np.meshgrid(*[np.arange(cfg.size)] * 3, indexing="ij"), -1)
    solid = np.asarray(world.occupied(w, jnp.asarray(voxels)))
    np.testing.assert_array_equal(solid, truth == geometry.OCCUPIED)
    outside = jnp.array([[-1, 0, 0], [0, cfg.size, 0], [0, 0, -1], [cfg.size, 5, 5]])
    assert not np.asarray(world.occupied(w, outside)).any()
    assert not truth[0, 0, 0] == geometry.OCCUPIED  # the robots' start is free


def test_open_faces_hand_worked():
    height = np.zeros((8, 8), np.int32)
    height[5, 5], height[6, 5], height[0, 3] = 4, 2, 3
    windows = [(5, 5, 1), (5, 5, 3), (0, 3, 2)]
    w = world.World.build(jnp.asarray(height), jnp.asarray(windows, jnp.int32),
                          jnp.ones(3, bool))
    np.testing.assert_array_equal(np.asarray(w.target_open), [  # -x, +x, -y, +y, +z
        [True, False, True, True, False],  # low on the tall column, beside the short one
        [True, True, True, True, True],  # above the short neighbour, on the roof
        [True, True, True, True, True],  # on the grid's edge (outside is air), on the roof
    ])
    np.testing.assert_array_equal(world.FACES.sum(axis=1), [-1, 1, -1, 1, 1])


def test_generated_windows_face_the_air_where_their_neighbours_are_free():
    cfg, w = city(5, layout="random")
    beside = w.target_voxel[:, None, :] + world.FACES
    truth = np.asarray(world.truth_occupancy(w, cfg.size))
    inside = np.all((beside >= 0) & (beside < cfg.size), axis=-1)
    solid = np.zeros(inside.shape, bool)
    solid[inside] = truth[tuple(beside[inside].T)] == geometry.OCCUPIED
    valid = w.target_valid
    np.testing.assert_array_equal(w.target_open[valid], ~solid[valid])
    assert w.target_open[valid].any(axis=1).all()  # facade windows are seen from somewhere


@pytest.mark.parametrize("placement", ["facade", "footprint"])
def test_varied_footprints_are_rectangles_in_range_with_windows_on_them(placement):
    cfg, w = city(6, layout="random", footprint=5, footprint_min=2, target_placement=placement)
    boxes = footprints(w.height)
    assert len(boxes) == cfg.n_buildings
    sides = np.array([hi - lo + 1 for lo, hi in boxes])
    assert sides.min() >= 2 and sides.max() <= 5 and len(np.unique(sides, axis=0)) > 4
    for lo, hi in boxes:  # one height per rectangle: nothing missing, nothing merged
        block = w.height[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1]
        assert (block > 0).all() and np.ptp(block) == 0
    check_windows(cfg, w)
    v = w.target_voxel[w.target_valid]
    labels, _ = ndimage.label(w.height > 0, structure=np.ones((3, 3)))
    assert len(np.unique(labels[v[:, 0], v[:, 1]])) > cfg.n_buildings // 2
    if placement == "footprint":  # interior columns of the larger footprints hold some
        padded = np.pad(w.height, 1)
        x, y, z = v[:, 0] + 1, v[:, 1] + 1, v[:, 2]
        walled = np.stack([padded[x - 1, y], padded[x + 1, y], padded[x, y - 1],
                           padded[x, y + 1]]) > z
        assert walled.all(axis=0).any()


def test_square_footprints_ignore_the_varied_draw():
    """footprint_min = footprint draws sides that are all the square's: the same city as
    footprint_min = 0 in its buildings, by its own key."""
    _, square = city(9, layout="random")
    _, drawn = city(9, layout="random", footprint_min=3)
    np.testing.assert_array_equal(square.height, drawn.height)


def test_impossible_configs_raise():
    with pytest.raises(ValueError, match="windows requested"):
        world.generate(jax.random.PRNGKey(0), WorldConfig(targets=(5000, 5000)))
    with pytest.raises(ValueError, match="do not fit"):
        world.generate(jax.random.PRNGKey(0), WorldConfig(buildings=400))
    with pytest.raises(ValueError, match="clearance"):
        world.generate(jax.random.PRNGKey(0), WorldConfig(clearance=0))
