"""Physics in the loop (jaxmripp.flight): the city in metres by hand, the quadrotor's
flight, the ray-cast depth camera against slab intersection, window sightings, crashes,
and one short mission of the shipped policy."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pybullet", reason="the flight extra: pip install -e .[flight]")

from jaxmripp.flight import city as citymod  # noqa: E402
from jaxmripp.flight.city import CityFrame  # noqa: E402
from jaxmripp.flight.mission import MissionSettings, camera_for, fly_mission  # noqa: E402
from jaxmripp.flight.scene import Scene  # noqa: E402
from jaxmripp.flight.team import load_team  # noqa: E402
from jaxmripp.runtime.depth import DepthCamera  # noqa: E402
from scripts import load_script  # noqa: E402
from test_runtime_depth import LOOK_X, box_depth  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
FRAME = CityFrame(extent=(10.0, 10.0, 5.0), ground_clearance=0.5, inset=0.2, core=0.25)


def two_blocks():
    """G = 10 (1 m x 1 m x 0.5 m voxels): a 3 x 3 block 4 voxels tall at x 2..4, y 3..5 and
    a 2 x 2 block 2 voxels tall at x 7..8, y 7..8."""
    height = np.zeros((10, 10), int)
    height[2:5, 3:6] = 4
    height[7:9, 7:9] = 2
    return height


def yawed(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ LOOK_X


def test_city_boxes_and_window_faces_by_hand():
    city = citymod.from_height_map(two_blocks(), [[2, 3, 1], [3, 3, 0]], FRAME)
    order = np.argsort(city.box_centre[:, 0])
    lo = (city.box_centre - city.box_half)[order]
    hi = (city.box_centre + city.box_half)[order]
    # Walls 0.2 of a voxel in from the block, roof 0.2 x 0.5 m below it, down to the ground.
    np.testing.assert_allclose(lo, [[2.2, 3.2, 0.0], [7.2, 7.2, 0.0]])
    np.testing.assert_allclose(hi, [[4.8, 5.8, 0.5 + 2.0 - 0.1], [8.8, 8.8, 0.5 + 1.0 - 0.1]])
    # The corner window has two outside faces, the edge window one.
    assert city.face_window.tolist() == [0, 0, 1]
    np.testing.assert_allclose(city.face_point, [[2.2, 3.5, 1.25], [2.5, 3.2, 1.25],
                                                 [3.5, 3.2, 0.75]])
    np.testing.assert_allclose(city.face_normal, [[-1, 0, 0], [0, -1, 0], [0, -1, 0]])


def test_city_refuses_hidden_windows_and_walls_outside_the_core():
    with pytest.raises(ValueError, match=r"\[3, 4, 0\] has no face"):
        citymod.from_height_map(two_blocks(), [[3, 4, 0]], FRAME)
    with pytest.raises(ValueError, match="inset"):
        CityFrame(inset=0.3, core=0.25)


def test_the_same_seed_gives_the_voxel_worlds_city():
    team = load_team(REPO / "pretrained/default")
    city = citymod.generate(7, team.world, CityFrame())
    import jax

    from jaxmripp.sim import world as worldmod

    world = worldmod.generate(jax.random.key(7), team.world)
    np.testing.assert_array_equal(city.height, np.asarray(world.height))
    assert city.n_windows == int(world.target_valid.sum())
    # Every box stands inside the columns of its building.
    voxel = city.voxel_metres
    for lo, hi in zip(city.box_centre - city.box_half, city.box_centre + city.box_half):
        cells = city.height[int(lo[0] // voxel[0]):int(hi[0] // voxel[0]) + 1,
                            int(lo[1] // voxel[1]):int(hi[1] // voxel[1]) + 1]
        assert (cells > 0).all()


def test_a_drone_flies_its_line_at_the_speed_limit():
    scene = Scene(citymod.from_height_map(np.zeros((10, 10), int), np.zeros((0, 3)), FRAME),
                  np.array([[1.0, 1.0, 1.0]]), np.array([0.0]))
    drone = scene.drones[0]
    start, goal = np.array([1.0, 1.0, 1.0]), np.array([5.0, 4.0, 3.0])
    drone.fly_to(goal, math.pi / 2)
    speed = error = 0.0
    while not drone.arrived() and scene.time < 30:
        scene.step()
        at, velocity, _, _ = drone.state()
        speed = max(speed, np.linalg.norm(velocity))
        d = goal - start
        t = np.clip((at - start) @ d / (d @ d), 0, 1)
        error = max(error, np.linalg.norm(at - (start + t * d)))
    at, _, rotation, _ = drone.state()
    scene.close()
    assert np.linalg.norm(at - goal) <= 0.05
    assert math.atan2(rotation[1, 0], rotation[0, 0]) == pytest.approx(math.pi / 2, abs=0.05)
    assert 0.8 < speed <= 1.0 and error < 0.05
    assert scene.time < 2.2 * np.linalg.norm(goal - start)  # 1.875 / 0.95 x its length
    assert scene.crashes == []


def test_the_depth_camera_matches_slab_intersection():
    city = citymod.from_height_map(two_blocks(), np.zeros((0, 3)), FRAME)
    scene = Scene(city, np.array([[0.5, 9.5, 4.0]]), np.array([0.0]))
    camera = DepthCamera.square(24, 90.0, max_range=9.0, min_range=0.1)
    position, rotation = np.array([0.6, 4.3, 1.2]), yawed(0.1)
    depth = scene.depth_image(camera, position, rotation)
    scene.close()
    i = int(np.argmin(city.box_centre[:, 0]))
    lo, hi = city.box_centre[i] - city.box_half[i], city.box_centre[i] + city.box_half[i]
    expected = box_depth(camera, position, rotation, lo, hi)
    # The ground z = 0 (a plane: only rays going down meet it).
    rays = camera.directions() @ rotation.T
    with np.errstate(divide="ignore"):
        t = np.where(rays[..., 2] < 0, -position[2] / rays[..., 2], np.inf)
    ground = np.where(t <= camera.max_range, t * camera.directions()[..., 2], np.inf)
    expected = np.minimum(expected, ground)
    assert np.isfinite(expected).sum() > 200 and np.isinf(expected).sum() > 20
    np.testing.assert_array_equal(np.isinf(depth), np.isinf(expected))
    finite = np.isfinite(expected)
    np.testing.assert_allclose(depth[finite], expected[finite], atol=2e-3)


def test_windows_are_seen_in_view_facing_and_unoccluded():
    """Windows: 0 on the small block's corner (faces -x and -y), 1 on the big block's +y
    face, 2 on the big block's -x face."""
    city = citymod.from_height_map(two_blocks(), [[7, 7, 0], [3, 5, 1], [2, 4, 1]], FRAME)
    scene = Scene(city, np.array([[0.5, 9.5, 4.0]]), np.array([0.0]))
    camera = DepthCamera.square(32, 90.0, max_range=9.0, min_range=0.1)
    # East of the big block, looking east: 0 ahead; 1 and 2 behind.
    assert scene.windows_seen(camera, np.array([5.5, 7.5, 0.75]), yawed(0.0)).tolist() == [0]
    # North of the big block, looking south: 1 ahead; 2 faces west, 0 is out of the image.
    assert scene.windows_seen(camera, np.array([3.5, 8.5, 1.2]),
                              yawed(-math.pi / 2)).tolist() == [1]
    # Far west, looking east: 0 and 1 in view and in sight; 2 is outside the image.
    assert scene.windows_seen(camera, np.array([0.5, 7.5, 0.75]), yawed(0.0)).tolist() == [0, 1]
    scene.close()
    # A thin building at x = 5 between that camera and window 0 hides it.
    walled = two_blocks()
    walled[5, 6:9] = 3
    city = citymod.from_height_map(walled, [[7, 7, 0], [3, 5, 1]], FRAME)
    scene = Scene(city, np.array([[0.5, 9.5, 4.0]]), np.array([0.0]))
    assert scene.windows_seen(camera, np.array([0.5, 7.5, 0.75]), yawed(0.0)).tolist() == [1]
    scene.close()


def test_contacts_are_crashes():
    city = citymod.from_height_map(two_blocks(), np.zeros((0, 3)), FRAME)
    scene = Scene(city, np.array([[1.0, 4.5, 1.0], [8.0, 1.0, 1.0]]), np.array([0.0, 0.0]))
    scene.drones[0].fly_to(np.array([3.5, 4.5, 1.0]), 0.0)  # into the big block
    scene.drones[1].fly_to(np.array([8.0, 1.0, -1.0]), 0.0)  # into the ground
    while scene.time < 8:
        scene.step()
    scene.close()
    first = {}
    for crash in scene.crashes:
        first.setdefault(crash.drone, crash.other)
    assert first == {0: "building", 1: "ground"}  # drone 0 then tumbles to the ground
    # Each contact counts once when it begins: a few events, not one per step.
    assert len(scene.crashes) < 20


def test_a_team_flies_at_a_radio_range_given_instead_of_the_exports(capsys):
    team = load_team(REPO / "pretrained/default")
    near = load_team(REPO / "pretrained/default", radio_range=0.3)
    assert team.spec.radio_range != 0.3
    assert near.spec == dataclasses.replace(team.spec, radio_range=0.3)
    flight = load_script("benchmarks/flight.py")
    # The config's rules for radio.range: at least 0 and above radio.collision_distance.
    for bad, wrong, allowed in (("0", "radio.collision_distance: got 0.05",
                                 "less than radio.range = 0.0"),
                                ("-0.5", "radio.range: got -0.5", "a number in [0, inf]"),
                                ("nan", "radio.range: got nan", "a number")):
        with pytest.raises(SystemExit) as refused:
            flight.main(["--radio-range", bad, "--worlds", "1"])
        assert refused.value.code == 2
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and error[0].startswith(f"error: {wrong}")
        assert f"allowed: {allowed}" in error[0]


def test_a_short_mission_of_the_shipped_policy_is_safe():
    team = load_team(REPO / "pretrained/default")
    spec = team.spec
    settings = MissionSettings(budget=2.0)
    city = citymod.generate(3, team.world, settings.frame)
    result = fly_mission(city, spec, team.exported, "policy", settings, seed=3,
                         pad_spacing=team.pad_spacing)
    assert result.crashes == [] and result.false_free == 0 and result.late_arrivals == 0
    assert result.max_speed <= 1.0 and result.track_error < 0.1
    assert result.rounds >= 2 and sum(len(w) - 1 for w in result.waypoints) >= 2
    # Windows are counted when first seen: the flights find more than the pads' views.
    first_flight = result.path_time[1]
    at_pads = np.sum(result.found_time < first_flight)
    assert at_pads < np.sum(result.found) < city.n_windows
    assert np.all(result.found_time[result.found] <= result.sim_seconds)
    # Every window found faces, from within the camera's range, a point some drone flew
    # to (its waypoints, pads included; the camera sits within 0.2 m of them).
    reach = camera_for(spec, settings.frame, settings).max_range
    points = np.concatenate([np.asarray(w) for w in result.waypoints])  # (K, 3) metres
    offset = points[None] - city.face_point[:, None]  # (faces, K, 3)
    in_front = np.einsum("fkc,fc->fk", offset, city.face_normal) > 0
    near = np.linalg.norm(offset, axis=-1) <= reach + 0.2
    seeable = np.zeros(city.n_windows, bool)
    np.logical_or.at(seeable, city.face_window, np.any(in_front & near, axis=1))
    assert np.all(seeable[result.found]), np.nonzero(result.found & ~seeable)
    assert not seeable.all()  # the condition is no formality in this city
    # The drones flew the signed radio: no message refused.
    assert result.refused_messages == 0
    print(f"{result.pct:.1f}% found, {at_pads} from the pads; {result.map_conflicts} map "
          "conflicts between the drones' depth maps")
