"""The physics scene: a city, the ground and a team of quadrotors in one pybullet world.

The depth camera is a ray caster against the scene's collision shapes (pybullet's
`rayTestBatch`, one ray per pixel centre), mounted on each drone looking along its body x
axis (the heading). Windows are ground truth, as in the paper: a window counts as seen
from a camera when one of its faces lies inside the image, within range, faces the camera
and the straight line to it meets nothing. A crash is a contact of a drone's body with a
building, the ground or another drone, read from the physics engine after every step and
counted once when it begins (a drone resting against a wall is one crash, not one per
step).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxmripp.flight.city import City
from jaxmripp.flight.quadrotor import GRAVITY, Quadrotor, QuadrotorParams
from jaxmripp.runtime.depth import DepthCamera

# Camera axes (x right, y down, z forward) in the body frame (x forward, y left, z up).
CAMERA_IN_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
RAY_BATCH = 16384  # pybullet's largest rayTestBatch
WINDOW_LIFT = 0.02  # metres in front of the wall where a window's sight line ends


@dataclasses.dataclass(frozen=True)
class Crash:
    time: float  # seconds of simulated time
    drone: int
    other: str  # "building", "ground" or "drone <id>"


class Scene:
    """A pybullet world (DIRECT, no window) with the city, the ground and the drones."""

    def __init__(self, city: City, starts_m: np.ndarray, yaws: np.ndarray,
                 params: QuadrotorParams = QuadrotorParams(), physics_hz: int = 240):
        import pybullet

        self.p = pybullet
        self.city, self.params, self.dt = city, params, 1.0 / physics_hz
        self.client = pybullet.connect(pybullet.DIRECT)
        p, c = pybullet, self.client
        p.setGravity(0, 0, -GRAVITY, physicsClientId=c)
        p.setTimeStep(self.dt, physicsClientId=c)
        span = max(city.frame.extent) * 2
        ground = p.createCollisionShape(p.GEOM_BOX, halfExtents=[span, span, 0.05],
                                        physicsClientId=c)
        ground_look = p.createVisualShape(p.GEOM_BOX, halfExtents=[span, span, 0.05],
                                          rgbaColor=[0.55, 0.6, 0.55, 1], physicsClientId=c)
        self.ground = p.createMultiBody(0, ground, ground_look, [0, 0, -0.05],
                                        physicsClientId=c)
        self.buildings = set()
        for centre, half in zip(city.box_centre, city.box_half):
            shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=list(half),
                                           physicsClientId=c)
            look = p.createVisualShape(p.GEOM_BOX, halfExtents=list(half),
                                       rgbaColor=[0.75, 0.72, 0.68, 1], physicsClientId=c)
            self.buildings.add(p.createMultiBody(0, shape, look, list(centre),
                                                 physicsClientId=c))
        self.drones = [Quadrotor(c, params, start, yaw) for start, yaw in zip(starts_m, yaws)]
        self.body_to_drone = {d.body: i for i, d in enumerate(self.drones)}
        self.time = 0.0
        self.crashes: list[Crash] = []
        self._touching: set[tuple[int, str]] = set()  # (drone, other) in contact now

    def close(self) -> None:
        self.p.disconnect(physicsClientId=self.client)

    # -----------------------------------------------------------------------------------
    # Flying

    def step(self) -> None:
        """One physics step: every drone's controller, the engine, then the contacts."""
        for drone in self.drones:
            drone.apply_control(self.dt)
        self.p.stepSimulation(physicsClientId=self.client)
        self.time += self.dt
        touching = set()
        for i, drone in enumerate(self.drones):
            for contact in self.p.getContactPoints(bodyA=drone.body,
                                                   physicsClientId=self.client):
                other = contact[2]
                touching.add((i, "ground" if other == self.ground else "building"
                              if other in self.buildings
                              else f"drone {self.body_to_drone.get(other)}"))
        self.crashes += [Crash(self.time, i, name) for i, name in sorted(touching - self._touching)]
        self._touching = touching

    def positions(self) -> np.ndarray:
        return np.array([d.state()[0] for d in self.drones])

    # -----------------------------------------------------------------------------------
    # Sensing

    def camera_pose(self, drone: int) -> tuple[np.ndarray, np.ndarray]:
        """(position (3,), rotation camera -> world (3, 3)) of a drone's camera now."""
        position, _, rotation, _ = self.drones[drone].state()
        return position, rotation @ CAMERA_IN_BODY

    def depth_image(self, camera: DepthCamera, position: np.ndarray, rotation: np.ndarray
                    ) -> np.ndarray:
        """(H, W) z-depth in metres (+inf: nothing within range) by casting one ray per
        pixel centre from `min_range` to `max_range`."""
        rays = camera.directions()
        world = (rays @ rotation.T).reshape(-1, 3)
        hits = self._cast(position + world * camera.min_range,
                          position + world * camera.max_range)
        fraction = np.array([h[2] if h[0] >= 0 else 1.0 for h in hits])
        length = camera.min_range + fraction * (camera.max_range - camera.min_range)
        depth = (length * rays[..., 2].reshape(-1)).reshape(camera.height, camera.width)
        return np.where(fraction.reshape(depth.shape) < 1.0, depth, np.inf)

    def windows_seen(self, camera: DepthCamera, position: np.ndarray, rotation: np.ndarray
                     ) -> np.ndarray:
        """Indices of the windows with a face inside the image, within range, facing the
        camera and in clear sight."""
        city = self.city
        if not len(city.face_point):
            return np.zeros(0, np.int64)
        offset = city.face_point - position
        local = offset @ rotation  # camera frame
        z = local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = camera.cx + camera.fx * local[:, 0] / z
            v = camera.cy + camera.fy * local[:, 1] / z
        inside = (z > 0) & (u >= -0.5) & (u <= camera.width - 0.5) \
            & (v >= -0.5) & (v <= camera.height - 0.5)
        distance = np.linalg.norm(offset, axis=1)
        facing = np.einsum("ij,ij->i", offset, city.face_normal) < 0
        candidates = np.nonzero(inside & facing & (distance <= camera.max_range)
                                & (distance > camera.min_range))[0]
        if not len(candidates):
            return np.zeros(0, np.int64)
        ends = city.face_point[candidates] + WINDOW_LIFT * city.face_normal[candidates]
        direction = (ends - position) / distance[candidates, None]
        starts = position + direction * camera.min_range
        clear = np.array([h[0] < 0 for h in self._cast(starts, ends)], bool)
        return np.unique(city.face_window[candidates[clear]])

    def _cast(self, starts: np.ndarray, ends: np.ndarray) -> list:
        """pybullet's rayTestBatch over any number of rays: one hit tuple per ray (body
        id -1 where the ray meets nothing; [2] is the hit fraction)."""
        hits = []
        for lo in range(0, len(starts), RAY_BATCH):
            hits += self.p.rayTestBatch(starts[lo:lo + RAY_BATCH].tolist(),
                                        ends[lo:lo + RAY_BATCH].tolist(),
                                        physicsClientId=self.client)
        return hits
