"""One mission: a team of simulated quadrotors, each planning with its own onboard runtime.

Every round, on every drone: the camera's depth images at the pose reached go into its
`OnboardPlanner` (`sense_depth`), with the number of windows in sight; the planners talk
by radio as in `jaxmripp.demo` (messages, map deltas, intents: JSON bytes to the drones
within `radio.range` of each other); each `decide`s and `resolve`s. Then every drone that
does not hover flies its straight line to the chosen pose under its own position
controller (the physics engine integrates all of them at once) and turns to the chosen
heading; the round ends when all have arrived. The mission ends when every drone hovers,
or after the round limit.

The team's radio is signed: every drone holds the team key, derived from the mission's
seed (`jaxmripp.runtime.team_key(seed)`: reproducible, no secret; a real team draws one
with `team_key()`), and takes only messages signed with it (`MissionSettings.signed`).

Positions go to the planner as the waypoint it chose (the drones fly to within a few
centimetres of it; localisation is perfect, as in the paper); images and window sightings
come from the camera's true pose. Windows are counted once, by ground truth, when a drone
sees them (`Scene.windows_seen`); crashes are every contact the engine reports.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from jaxmripp.flight.city import City, CityFrame
from jaxmripp.flight.quadrotor import QuadrotorParams
from jaxmripp.flight.scene import Crash, Scene
from jaxmripp.flight.team import exchange, pads
from jaxmripp.runtime.auth import team_key
from jaxmripp.runtime.depth import DepthCamera
from jaxmripp.runtime.planner import OnboardPlanner
from jaxmripp.runtime.weights import ExportedPolicy, RuntimeSpec
from jaxmripp.spec.grid import FREE, HEADING_ANGLES

PLANNERS = ("policy", "nbv", "greedy", "random")


@dataclasses.dataclass(frozen=True)
class MissionSettings:
    budget: float = 7.0  # team budget in unit-cube lengths (the paper's physics experiment)
    pixels: int = 64  # depth image side
    min_range: float = 0.1  # metres: the camera sees past the drone's own body
    physics_hz: int = 240
    round_limit_s: float = 120.0  # simulated seconds a round's flights may take
    max_rounds: int | None = None  # default: enough for the budget
    record_every_s: float = 1.0  # positions kept for the pictures
    sectors: bool = False  # drones keep to their sectors (OnboardPlanner(sectors=True))
    signed: bool = True  # the radio carries the team key's tags (jaxmripp.runtime.auth)
    frame: CityFrame = CityFrame()
    quadrotor: QuadrotorParams = QuadrotorParams()


@dataclasses.dataclass
class MissionResult:
    planner: str
    windows: int
    found: np.ndarray  # (T,) bool: seen by some drone
    crashes: list[Crash]
    rounds: int
    late_arrivals: int  # flights that had not arrived when their round's time ran out
    false_free: int  # voxels inside a building that some drone's map holds FREE
    refused_messages: int  # radio messages some drone refused (none in an honest team)
    map_conflicts: int  # voxels of merged deltas held FREE by one drone, OCCUPIED by another
    sim_seconds: float
    wall_seconds: float
    decision_ms: list[float]  # per robot decision (decide + resolve)
    sense_ms: list[float]  # per robot depth -> map update
    max_speed: float  # m/s, fastest any drone flew
    track_error: float  # metres, farthest any drone strayed from its line of flight
    path_time: np.ndarray  # (K,) seconds
    path: np.ndarray  # (K, N, 3) metres
    found_time: np.ndarray  # (T,) seconds when first seen (inf: never)
    waypoints: list[list[np.ndarray]]  # per drone, the poses it flew to (metres)

    @property
    def pct(self) -> float:
        return 100.0 * float(self.found.mean()) if self.windows else 0.0

    def figures(self) -> dict:
        """The mission's figures, JSON-ready."""
        return {
            "planner": self.planner, "pct": round(self.pct, 3), "windows": self.windows,
            "crashes": len(self.crashes),
            "crash_list": [dataclasses.asdict(c) for c in self.crashes[:20]],
            "rounds": self.rounds, "late_arrivals": self.late_arrivals,
            "false_free_voxels": self.false_free, "refused_messages": self.refused_messages,
            "map_conflicts": self.map_conflicts, "sim_seconds": round(self.sim_seconds, 2),
            "wall_seconds": round(self.wall_seconds, 2),
            "sim_realtime_factor": round(self.sim_seconds / self.wall_seconds, 2),
            "decision_ms_median": round(float(np.median(self.decision_ms)), 3),
            "sense_ms_median": round(float(np.median(self.sense_ms)), 3),
            "max_speed": round(self.max_speed, 3), "track_error_m": round(self.track_error, 4),
        }


def camera_for(spec: RuntimeSpec, frame: CityFrame, settings: MissionSettings
               ) -> DepthCamera:
    """The drones' depth camera: the spec's field of view, its range as a fraction of the
    city's horizontal size."""
    reach = spec.sensor_range * max(frame.extent[0], frame.extent[1])
    return DepthCamera.square(settings.pixels, spec.fov_deg, reach, settings.min_range)


def fly_mission(city: City, spec: RuntimeSpec, policy: ExportedPolicy | None, planner: str,
                settings: MissionSettings = MissionSettings(), seed: int = 0,
                pad_spacing: float = 0.06, progress=None) -> MissionResult:
    """Flies one mission with `planner` (one of PLANNERS: a runtime mode) on every drone.
    progress(round, result_so_far_pct) is called after every round when given."""
    if planner not in PLANNERS:
        raise ValueError(f"planner: got {planner!r}; allowed: {', '.join(PLANNERS)}")
    if planner == "policy" and policy is None:
        raise ValueError("planner 'policy' needs exported weights (--export)")
    if city.size != spec.size:
        raise ValueError(f"city of G = {city.size} for a policy of G = {spec.size}")
    wall_start = time.perf_counter()
    n = spec.team_size
    frame, grid = settings.frame, settings.frame.grid
    camera = camera_for(spec, frame, settings)
    per_robot = settings.budget / n
    rounds = settings.max_rounds or max(spec.max_steps,
                                        int(math.ceil(per_robot / spec.shell[0])) + 4)
    planners = [OnboardPlanner(spec, i, per_robot, team_size=n,
                               policy=policy.policy if policy is not None else None,
                               mode=planner, max_steps=rounds, seed=seed * 1000 + i,
                               sectors=settings.sectors,
                               team_key=team_key(seed) if settings.signed else None)
                for i in range(n)]
    position = pads(spec.start, n, pad_spacing)
    heading = np.full(n, spec.start_heading, np.int64)
    scene = Scene(city, grid.to_metres(position), HEADING_ANGLES[heading].astype(float),
                  settings.quadrotor, settings.physics_hz)
    found_time = np.full(city.n_windows, np.inf)
    decision_ms, sense_ms = [], []
    path_time, path = [0.0], [scene.positions()]
    waypoints = [[grid.to_metres(p)] for p in position]
    late, max_speed, track_error, step = 0, 0.0, 0.0, 0
    try:
        for step in range(rounds + 1):
            for i, robot in enumerate(planners):
                images, seen = _look(scene, i, camera)
                found_time[seen] = np.minimum(found_time[seen], scene.time)
                start = time.perf_counter()
                # The windows in sight name their voxels (what the target belief counts).
                robot.sense_depth(position[i], int(heading[i]), images, camera, grid,
                                  len(seen), windows=city.window_voxel[seen])
                sense_ms.append(1e3 * (time.perf_counter() - start))
            decisions = _plan(planners, position, spec, decision_ms)
            if progress is not None:
                progress(step, 100.0 * np.isfinite(found_time).mean())
            if all(d.hover for d in decisions):
                break
            for i, d in enumerate(decisions):
                if not d.hover:
                    position[i], heading[i] = d.position, d.heading
                    waypoints[i].append(grid.to_metres(d.position))
                    scene.drones[i].fly_to(grid.to_metres(d.position),
                                           float(HEADING_ANGLES[d.heading]))
            speed, error, on_time = _fly(scene, settings, path_time, path)
            max_speed, track_error = max(max_speed, speed), max(track_error, error)
            late += not on_time
    finally:
        scene.close()
    solid = (np.arange(city.size)[None, None, :] < city.height[:, :, None]).reshape(-1)
    return MissionResult(
        planner=planner, windows=city.n_windows, found=np.isfinite(found_time),
        crashes=list(scene.crashes), rounds=step, late_arrivals=late,
        false_free=sum(int(np.sum((p.map.codes == FREE) & solid)) for p in planners),
        refused_messages=sum(sum(p.rejected_messages.values()) for p in planners),
        map_conflicts=sum(p.sharing.conflicts for p in planners),
        sim_seconds=scene.time,
        wall_seconds=time.perf_counter() - wall_start, decision_ms=decision_ms,
        sense_ms=sense_ms, max_speed=max_speed, track_error=track_error,
        path_time=np.asarray(path_time), path=np.asarray(path), found_time=found_time,
        waypoints=waypoints)


def _look(scene: Scene, drone: int, camera: DepthCamera):
    """The depth image ([(depth, camera position, rotation)], as `sense_depth` takes it)
    and the windows seen by one drone where it is."""
    position, rotation = scene.camera_pose(drone)
    return ([(scene.depth_image(camera, position, rotation), position, rotation)],
            scene.windows_seen(camera, position, rotation))


def _plan(planners: list[OnboardPlanner], position: np.ndarray, spec: RuntimeSpec,
          decision_ms: list[float]):
    """One radio round and decision on every drone (the order of `jaxmripp.demo`)."""
    exchange([p.message() for p in planners], position, spec.radio_range,
             lambda i, data: planners[i].receive(data))
    if spec.share_maps:
        exchange([p.map_message() for p in planners], position, spec.radio_range,
                 lambda i, data: planners[i].receive_map(data))
    times = []
    for p in planners:
        start = time.perf_counter()
        p.decide()
        times.append(time.perf_counter() - start)
    exchange([p.intent_message() for p in planners], position, spec.radio_range,
             lambda i, data: planners[i].receive_intent(data))
    decisions = []
    for p, spent in zip(planners, times):
        start = time.perf_counter()
        decisions.append(p.resolve())
        decision_ms.append(1e3 * (spent + time.perf_counter() - start))
    return decisions


def _fly(scene: Scene, settings: MissionSettings, path_time: list, path: list):
    """Steps the physics until every drone has arrived (or the round's time is up) ->
    (fastest speed, largest distance from a line of flight, all arrived)."""
    every = max(1, round(settings.record_every_s * settings.physics_hz))
    limit = int(settings.round_limit_s * settings.physics_hz)
    speed = error = 0.0
    segments = [(d.start, d.goal) for d in scene.drones]
    for k in range(1, limit + 1):
        scene.step()
        if k % 4 == 0 or k == limit:
            for drone, (a, b) in zip(scene.drones, segments):
                at, velocity, _, _ = drone.state()
                speed = max(speed, float(np.linalg.norm(velocity)))
                error = max(error, _distance_to_segment(at, a, b))
        if k % every == 0:
            path_time.append(scene.time)
            path.append(scene.positions())
        if k % 4 == 0 and all(d.arrived() for d in scene.drones):
            path_time.append(scene.time)
            path.append(scene.positions())
            return speed, error, True
    return speed, error, False


def _distance_to_segment(point, a, b) -> float:
    d = b - a
    length2 = float(d @ d)
    t = 0.0 if length2 == 0 else min(max(float((point - a) @ d) / length2, 0.0), 1.0)
    return float(np.linalg.norm(point - (a + t * d)))
