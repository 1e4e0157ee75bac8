"""A quadrotor in pybullet: a rigid body with collective thrust along its own z axis and
body torques, flown by a geometric position / attitude controller.

The body is the size and mass of a Crazyflie 2 (the drone of gym-pybullet-drones, which
the paper flew): 27 g, 0.12 m across the propellers, thrust-to-weight 2.25. The physics
engine integrates it with gravity and inertia; the controller only sees the body's state
and commands a thrust magnitude and a torque, as a flight controller would. Positions here
are in metres.

Controller (Lee, Leok and McClamroch, "Geometric tracking control of a quadrotor UAV on
SE(3)", 2010): a reference point moves along the commanded segment on a minimum-jerk
profile whose peak speed is `cruise` x the speed limit; a PD law on the error to it plus
its acceleration gives the wanted acceleration; thrust points the body's z axis along it
(tilt limited), and a PD law on the rotation error turns the body there, yawed to the
commanded heading.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

GRAVITY = 9.81


@dataclasses.dataclass(frozen=True)
class QuadrotorParams:
    mass: float = 0.027  # kg
    inertia: tuple[float, float, float] = (1.4e-5, 1.4e-5, 2.17e-5)  # kg m^2, body axes
    size: tuple[float, float, float] = (0.12, 0.12, 0.03)  # m, collision box incl. rotors
    thrust_to_weight: float = 2.25
    max_tilt_deg: float = 30.0
    max_speed: float = 1.0  # m/s
    cruise: float = 0.95  # the reference's peak speed, as a fraction of max_speed
    position_gain: float = 9.0  # 1/s^2
    velocity_gain: float = 6.0  # 1/s
    attitude_frequency: float = 25.0  # rad/s, closed-loop natural frequency
    attitude_damping: float = 0.9

    @property
    def radius(self) -> float:
        """Half the body's diagonal in the horizontal plane: its reach from the centre."""
        return 0.5 * math.hypot(self.size[0], self.size[1])


def _rotation_error(rotation: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    e = 0.5 * (wanted.T @ rotation - rotation.T @ wanted)
    return np.array([e[2, 1], e[0, 2], e[1, 0]])


def wanted_rotation(thrust_direction: np.ndarray, yaw: float) -> np.ndarray:
    """The rotation whose z axis is `thrust_direction` and whose x axis points as close to
    the yaw heading as that allows."""
    b3 = thrust_direction / np.linalg.norm(thrust_direction)
    heading = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    b2 = np.cross(b3, heading)
    b2 /= np.linalg.norm(b2)
    return np.stack([np.cross(b2, b3), b2, b3], axis=1)


def control(params: QuadrotorParams, position: np.ndarray, velocity: np.ndarray,
            rotation: np.ndarray, rate_body: np.ndarray, reference: np.ndarray,
            reference_velocity: np.ndarray, reference_accel: np.ndarray, yaw: float
            ) -> tuple[float, np.ndarray]:
    """One control step -> (thrust in N along the body z axis, torque (3,) in N m in the
    body frame). rotation: body -> world; rate_body: angular velocity in body axes."""
    m, g = params.mass, GRAVITY
    accel = params.position_gain * (reference - position) \
        + params.velocity_gain * (reference_velocity - velocity) + reference_accel
    accel[2] += g
    # Tilt limit: keep the vertical part, shorten the horizontal part.
    horizontal = math.hypot(accel[0], accel[1])
    limit = accel[2] * math.tan(math.radians(params.max_tilt_deg))
    if horizontal > limit > 0:
        accel[:2] *= limit / horizontal
    accel[2] = max(accel[2], 0.2 * g)
    wanted = wanted_rotation(accel, yaw)
    thrust = min(m * float(accel @ rotation[:, 2]), params.thrust_to_weight * m * g)
    inertia = np.asarray(params.inertia)
    w, z = params.attitude_frequency, params.attitude_damping
    torque = -inertia * w * w * _rotation_error(rotation, wanted) \
        - inertia * 2 * z * w * rate_body + np.cross(rate_body, inertia * rate_body)
    return max(thrust, 0.0), torque


class Quadrotor:
    """One drone in a pybullet client: its body and its controller's reference."""

    def __init__(self, client, params: QuadrotorParams, position, yaw: float = 0.0):
        import pybullet

        self.p, self.client, self.params = pybullet, client, params
        half = [s / 2 for s in params.size]
        shape = pybullet.createCollisionShape(pybullet.GEOM_BOX, halfExtents=half,
                                              physicsClientId=client)
        visual = pybullet.createVisualShape(pybullet.GEOM_BOX, halfExtents=half,
                                            rgbaColor=[0.9, 0.2, 0.1, 1.0],
                                            physicsClientId=client)
        orientation = pybullet.getQuaternionFromEuler([0, 0, yaw])
        self.body = pybullet.createMultiBody(params.mass, shape, visual, list(position),
                                             orientation, physicsClientId=client)
        pybullet.changeDynamics(self.body, -1, localInertiaDiagonal=list(params.inertia),
                                linearDamping=0.0, angularDamping=0.0,
                                physicsClientId=client)
        self.start = np.asarray(position, float)
        self.goal = self.start.copy()
        self.yaw = float(yaw)
        self.elapsed = 0.0
        self.duration = 0.0

    def state(self):
        p = self.p
        position, quaternion = p.getBasePositionAndOrientation(self.body,
                                                                physicsClientId=self.client)
        velocity, rate = p.getBaseVelocity(self.body, physicsClientId=self.client)
        rotation = np.array(p.getMatrixFromQuaternion(quaternion)).reshape(3, 3)
        return (np.array(position), np.array(velocity), rotation,
                rotation.T @ np.array(rate))

    def fly_to(self, goal, yaw: float) -> None:
        """Starts a straight flight from where the drone is told it is to `goal`."""
        self.start = self.goal.copy()
        self.goal = np.asarray(goal, float)
        self.yaw = float(yaw)
        self.elapsed = 0.0
        # A minimum-jerk profile peaks at 1.875 x the mean speed.
        speed = self.params.cruise * self.params.max_speed
        self.duration = 1.875 * float(np.linalg.norm(self.goal - self.start)) / speed

    def reference(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The reference point, its velocity and its acceleration now."""
        if self.duration <= 0 or self.elapsed >= self.duration:
            return self.goal, np.zeros(3), np.zeros(3)
        u, T = self.elapsed / self.duration, self.duration
        d = self.goal - self.start
        s = u ** 3 * (10 - 15 * u + 6 * u * u)
        ds = 30 * u * u * (1 - u) ** 2 / T
        dds = 60 * u * (1 - u) * (1 - 2 * u) / T ** 2
        return self.start + s * d, ds * d, dds * d

    def apply_control(self, dt: float) -> None:
        """Computes and applies this step's thrust and torque (pybullet clears them after
        every stepSimulation)."""
        position, velocity, rotation, rate = self.state()
        thrust, torque = control(self.params, position, velocity, rotation, rate,
                                 *self.reference(), self.yaw)
        p = self.p
        p.applyExternalForce(self.body, -1, [0.0, 0.0, thrust], [0.0, 0.0, 0.0],
                             p.LINK_FRAME, physicsClientId=self.client)
        p.applyExternalTorque(self.body, -1, list(rotation @ torque), p.WORLD_FRAME,
                              physicsClientId=self.client)
        self.elapsed += dt

    def arrived(self, tolerance: float = 0.05, speed: float = 0.1,
                yaw_tolerance: float = 0.05) -> bool:
        position, velocity, rotation, _ = self.state()
        yaw = math.atan2(rotation[1, 0], rotation[0, 0])
        yaw_error = abs((yaw - self.yaw + math.pi) % (2 * math.pi) - math.pi)
        return (self.elapsed >= self.duration
                and np.linalg.norm(position - self.goal) <= tolerance
                and np.linalg.norm(velocity) <= speed and yaw_error <= yaw_tolerance)
