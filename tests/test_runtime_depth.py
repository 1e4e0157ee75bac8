"""Depth image -> map (jaxmripp.runtime.depth) against scenes worked out by hand: a wall at
a known distance and a box seen across its corner, with depth images computed here by
plane and slab intersection."""

from __future__ import annotations

import numpy as np
import pytest

from jaxmripp import config, export
from jaxmripp.runtime import InvalidPoseError, OnboardPlanner
from jaxmripp.runtime.depth import DepthCamera, GridFrame, observe, observe_many
from jaxmripp.spec.grid import FREE, OCCUPIED, UNKNOWN

G = 20
FRAME = GridFrame(origin=(0.0, 0.0, 0.0), extent=(G, G, G), core=0.25)  # 1 m voxels
# Camera looking along +x: camera x (right) = world -y, camera y (down) = world -z.
LOOK_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def unflatten(flat):
    return np.stack([flat // (G * G), flat // G % G, flat % G], axis=-1)


def box_depth(camera, position, rotation, lo, hi):
    """z-depth of an axis-aligned box by the slab method, +inf where a ray misses it or
    meets it beyond range."""
    rays = camera.directions() @ rotation.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - position) / rays
        t2 = (hi - position) / rays
    near = np.nanmax(np.minimum(t1, t2), axis=-1)
    far = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit = (near <= far) & (near > 0) & (near <= camera.max_range)
    return np.where(hit, near * camera.directions()[..., 2], np.inf)


def test_a_wall_at_a_known_distance():
    camera = DepthCamera.square(16, 60.0, max_range=9.0)
    position = np.array([2.5, 10.5, 10.5])
    depth = np.full((16, 16), 5.8)  # the plane x = 8.3: z-depth is the x distance
    flat, codes = observe(depth, camera, position, LOOK_X, FRAME, G)
    voxels = unflatten(flat)
    occupied, free = voxels[codes == OCCUPIED], voxels[codes == FREE]
    assert len(np.unique(flat)) == len(flat)
    assert set(occupied[:, 0]) == {8}
    # Hit points by hand: position + ray * 5.8 / cos, per pixel.
    rays = camera.directions() @ LOOK_X.T
    hits = position + rays * (5.8 / camera.directions()[..., 2])[..., None]
    expected = {tuple(v) for v in np.floor(hits).reshape(-1, 3).astype(int)}
    assert {tuple(v) for v in occupied} == expected
    assert free[:, 0].min() >= 2 and free[:, 0].max() <= 7
    for x in range(3, 8):  # straight ahead, every voxel's core is crossed
        assert (x, 10, 10) in {tuple(v) for v in free}


def test_a_box_leaves_no_building_voxel_free():
    """The box is its voxel block [11, 14) x [11, 14) x [0, 6) set in by 0.2 of a voxel.
    The camera flies in line with the block's side x = 11 and looks along it (+y): rays to
    its right meet the box, rays straight ahead graze the block's rim between its face and
    the wall, and none may mark a block voxel FREE."""
    lo, hi = np.array([11.2, 11.2, 0.0]), np.array([13.8, 13.8, 5.8])
    camera = DepthCamera.square(48, 90.0, max_range=12.0)
    position = np.array([11.1, 5.5, 3.1])
    look_y = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ LOOK_X
    depth = box_depth(camera, position, look_y, lo, hi)
    assert 100 < np.isfinite(depth).sum() < depth.size - 100

    def in_block(v):
        return (v[:, 0] >= 11) & (v[:, 0] < 14) & (v[:, 1] >= 11) & (v[:, 1] < 14) \
            & (v[:, 2] < 6)

    flat, codes = observe(depth, camera, position, look_y, FRAME, G)
    voxels = unflatten(flat)
    assert in_block(voxels[codes == OCCUPIED]).all()
    assert not in_block(voxels[codes == FREE]).any()
    assert {(12, 11, 3), (13, 11, 3)} <= {tuple(v) for v in voxels[codes == OCCUPIED]}
    assert (11, 8, 3) in {tuple(v) for v in voxels[codes == FREE]}


def test_rays_through_a_voxel_rim_prove_nothing():
    """A narrow camera turned 1 degree left of +y misses the box of the test above and its
    rays run through the rim of block voxels (11, 11..13, z): those stay UNKNOWN, and would
    be FREE without the core rule."""
    lo, hi = np.array([11.2, 11.2, 0.0]), np.array([13.8, 13.8, 5.8])
    camera = DepthCamera.square(8, 2.0, max_range=12.0)
    position = np.array([11.1, 5.5, 3.1])
    yaw = np.pi / 2 + np.radians(1.2)
    body = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    rotation = body @ LOOK_X
    depth = box_depth(camera, position, rotation, lo, hi)
    assert np.isinf(depth).all()
    rim = {(11, y, z) for y in (11, 12, 13) for z in (2, 3, 4)}
    flat, codes = observe(depth, camera, position, rotation, FRAME, G, step=0.05)
    assert not rim & {tuple(v) for v in unflatten(flat)}
    bare = GridFrame(FRAME.origin, FRAME.extent, core=0.0)
    flat, codes = observe(depth, camera, position, rotation, bare, G, step=0.05)
    assert rim & {tuple(v) for v in unflatten(flat[codes == FREE])}


def test_no_return_is_free_to_range_and_returns_outside_the_grid_mark_nothing():
    camera = DepthCamera.square(8, 60.0, max_range=4.0)
    position = np.array([5.5, 5.5, 0.5])
    flat, codes = observe(np.full((8, 8), np.inf), camera, position, LOOK_X, FRAME, G)
    assert (codes == FREE).all() and unflatten(flat)[:, 0].max() <= 9
    # Looking straight down at the ground 0.5 m below the grid's lowest face.
    down = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    above = np.array([5.5, 5.5, 1.5])
    depth = np.full((8, 8), 2.0)  # the plane z = -0.5
    flat, codes = observe(depth, camera, above, down, FRAME, G)
    assert (codes == FREE).all()


def test_occupied_in_one_image_wins_over_free_in_another():
    camera = DepthCamera.square(8, 40.0, max_range=9.0)
    wall = np.full((8, 8), 3.0)  # x = 5.5 + 3 = 8.5: voxel x 8 occupied
    open_view = np.full((8, 8), np.inf)
    a = ([wall, [5.5, 10.5, 10.5], LOOK_X])
    b = ([open_view, [5.5, 10.5, 10.5], LOOK_X])
    flat, codes = observe_many([b, a], camera, FRAME, G)
    voxels = {tuple(v): c for v, c in zip(unflatten(flat), codes)}
    assert voxels[(8, 10, 10)] == OCCUPIED
    assert len(set(flat.tolist())) == len(flat)


@pytest.mark.parametrize("depth, rotation, message", [
    (np.full((8, 7), 1.0), LOOK_X, "shape"),
    (np.where(np.eye(8) > 0, np.nan, 1.0), LOOK_X, r"pixel \(0, 0\) holds nan"),
    (np.full((8, 8), -1.0), LOOK_X, r"holds -1.0 \(64 bad pixels\)"),
    (np.full((8, 8), 1.0), 2 * LOOK_X, "rotation"),
])
def test_bad_depth_input_is_one_line(depth, rotation, message):
    camera = DepthCamera.square(8, 60.0, max_range=5.0)
    with pytest.raises(InvalidPoseError, match=message) as error:
        observe(depth, camera, [1.0, 1.0, 1.0], rotation, FRAME, G)
    assert "\n" not in str(error.value)


def test_bad_camera_and_frame_settings():
    with pytest.raises(ValueError, match="fov_deg"):
        DepthCamera.square(8, 180.0, 5.0)
    with pytest.raises(ValueError, match="range"):
        DepthCamera.square(8, 90.0, 5.0, min_range=6.0)
    with pytest.raises(ValueError, match="core"):
        GridFrame((0, 0, 0), (1, 1, 1), core=0.5)


def test_planner_sense_depth_keeps_what_it_knows_occupied():
    """sense_depth == sense(observe(...)), except that a voxel the map holds OCCUPIED is
    never turned FREE by a later image."""
    cfg = config.from_dict({"world": {"size": G}, "robots": {"count": 1}})
    spec = export.runtime_spec(cfg)
    camera = DepthCamera.square(9, 60.0, max_range=6.0)  # a ray on the axis
    position_m = np.array([2.5, 10.5, 10.5])
    unit = FRAME.to_unit(position_m)
    wall = np.full((9, 9), 4.0)  # voxel x 6 occupied
    images = [(wall, position_m, LOOK_X)]
    a = OnboardPlanner(spec, 0, 1.0, team_size=1)
    a.sense_depth(unit, 0, images, camera, FRAME, 0)
    b = OnboardPlanner(spec, 0, 1.0, team_size=1)
    b.sense(unit, 0, *observe_many(images, camera, FRAME, G), 0)
    np.testing.assert_array_equal(a.map.codes, b.map.codes)
    index = (6 * G + 10) * G + 10
    assert a.map.codes[index] == OCCUPIED
    a.decide(mode="random")
    a.resolve()
    a.sense_depth(unit, 0, [(np.full((9, 9), np.inf), position_m, LOOK_X)], camera, FRAME, 0)
    assert a.map.codes[index] == OCCUPIED
    assert a.map.codes[index + G * G] == FREE  # beyond it, seen through the open view
    assert b.map.codes[index + G * G] == UNKNOWN
