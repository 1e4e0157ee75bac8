"""View gain: how much of what a candidate pose would see is still unknown to the team.

Both sides compute these candidate features from a robot's map (with `radio.share_maps`,
what it and the robots it heard have seen): the JAX environment
(`jaxmripp.sim.view`) and the onboard runtime (`jaxmripp.runtime.view`). The gains are
integer sums times one float32 reciprocal, so both give the same float32 numbers: below,
dividing by the total weight or by shell[1] (constants) means multiplying by their float32
reciprocal, which is what XLA compiles such a division to; dividing by the cost is a
division. peer_distance is `jaxmripp.spec.vectors` arithmetic, the same bits on both.

Building tops
    Every map keeps, per column (x, y), top = 1 + the highest z mapped OCCUPIED in it, or 0
    when none is. It only grows: written with the map (a voxel observed OCCUPIED raises it)
    and merged by maximum when maps are shared. A column's *nearby top* is the largest top
    of the column and its four horizontal neighbours inside the grid, its *around top* the
    largest of the column and its eight neighbours (sides and corners).

Samples
    A pose looks along its heading from the centre of its voxel c. The gain rays are a
    RAYS_PER_SIDE x RAYS_PER_SIDE grid through the centres of equal cells of the image
    plane (the sensor's field of view); ray r samples the voxels c + floor(0.5 + d o_r) at
    distances d = SAMPLE_STEP, 2 SAMPLE_STEP, ..., S SAMPLE_STEP voxels, S = the largest
    count with S SAMPLE_STEP + sqrt(3) / 2 <= the sensor's range, so that every sampled
    voxel's centre is in range (o_r the unit direction, computed in float64 when the
    table is built; the table holds integer offsets). A sample is *clear* when no earlier
    sample of its ray is mapped OCCUPIED or lies outside the grid. A clear sample inside
    the grid that is mapped UNKNOWN is *unknown*; it is also *facade* when its height z is
    at most its column's facade top (and that top is > 0): unknown space beside or on a
    building the team knows, below its known roof -- where unseen facades, and windows,
    are. Each sample weighs d^2 (in voxel units: the volume one ray's share of the view
    covers at that distance, up to a constant).

    Two settings of the config's sensor section (`sensor.gain_occlusion`,
    `sensor.gain_facade`) fit these rules to a sensor that sees through buildings and to
    windows inside footprints (the reference's frustum and `world.target_placement:
    footprint`). Without occlusion a sample is clear when no earlier sample of its ray
    lies outside the grid: voxels mapped OCCUPIED no longer stop the ray. The facade top
    is the nearby top ("nearby": windows on facades are seen from the columns beside a
    building), the around top ("around": also the corners, where the part of a box
    building not yet seen lies diagonally from its one known column, as from a corner)
    or the column's own top ("column": a known building column's unknown voxels below
    its roof are where its unseen windows are).

Features (columns of `jaxmripp.spec.layout.FEATURES`)
    view_unknown          sum of the weights of unknown samples / sum of all weights (of
                          all R rays)
    view_facade           the same for facade samples
    view_unknown_per_cost view_unknown * (shell[1] / max(cost, COST_FLOOR)): gain per flight
    view_facade_per_cost  ... the same for view_facade
    peer_distance         min(PEER_CAP, distance from the candidate's position to the
                          nearest robot heard this round / shell[1]); PEER_CAP when none
                          is heard. Robots heard this round sit at the waypoints they last
                          flew to (their last intents): a robot sees where its team is.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from jaxmripp.spec.grid import HEADING_VECTORS, N_HEADINGS

RAYS_PER_SIDE = 3
SAMPLE_STEP = 1  # voxels between samples: a longer step tunnels through known walls
COST_FLOOR = 1e-3  # below any real flight or turn cost; guards padding candidates
PEER_CAP = 5.0  # shell lengths: "nobody near"
VIEW_FEATURES = ("view_unknown", "view_facade", "view_unknown_per_cost", "view_facade_per_cost")
INTENT_FEATURES = ("peer_distance",)
FACADE_TOPS = ("nearby", "around", "column")  # sensor.gain_facade: which tops mark facade voxels


def samples_per_ray(sensor_range: float, size: int) -> int:
    """S: samples per ray for a sensor range (fraction of the world) at G voxels: the most
    whose voxel centres stay within the range after rounding (by up to sqrt(3) / 2)."""
    return max(1, int(math.floor((sensor_range * size - math.sqrt(3) / 2) / SAMPLE_STEP)))


@functools.lru_cache(maxsize=None)
def gain_table(fov_deg: float, sensor_range: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    """offsets (4, R, S, 3) int32 voxel offsets of every sample per heading, ray and
    distance (R = RAYS_PER_SIDE^2, rays row-major over (right, up) image cells); weights
    (S,) int64, d^2 in voxel units."""
    n, s = RAYS_PER_SIDE, samples_per_ray(sensor_range, size)
    tan = math.tan(math.radians(fov_deg) / 2)
    u = tan * ((2 * np.arange(n) + 1) / n - 1)
    right_u, up_u = (x.ravel() for x in np.meshgrid(u, u, indexing="ij"))
    distance = SAMPLE_STEP * np.arange(1, s + 1, dtype=np.float64)
    offsets = np.zeros((N_HEADINGS, n * n, s, 3), np.int32)
    up = np.array([0.0, 0.0, 1.0])
    for h in range(N_HEADINGS):
        forward = HEADING_VECTORS[h].astype(np.float64)
        right = np.cross(forward, up)
        direction = forward + right_u[:, None] * right + up_u[:, None] * up
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        offsets[h] = np.floor(0.5 + distance[None, :, None] * direction[:, None, :])
    weights = (distance.astype(np.int64)) ** 2
    return offsets, weights
