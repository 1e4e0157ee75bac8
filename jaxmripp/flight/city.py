"""The voxel world as a city in metres: the same seed gives the same city in both.

`jaxmripp.sim.world.generate` draws a city of box buildings on a G^3 grid over the unit
cube. Here it is placed in a physical box (`CityFrame`: the paper's 60 m x 60 m x 30 m by
default, lifted `ground_clearance` above the ground so that the grid's lowest layer is
air). Each building is one box: its voxel block with the walls and the roof set in by
`inset` of a voxel, so that every voxel the block touches is OCCUPIED in the voxel world
and the box sits inside that block. A drone that flies only through voxels mapped FREE
(`jaxmripp.runtime.depth` marks FREE only voxels whose core a ray crossed, and the core is
smaller than the set-in block) keeps at least `inset` of a voxel from every wall.

Windows are the voxel world's window voxels; each is a point at the centre of every face
of its voxel that lies on the outside of the building, on the box's wall.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxmripp.runtime.depth import GridFrame


@dataclasses.dataclass(frozen=True)
class CityFrame:
    """Where the unit cube sits in metres and how buildings are set into their voxels."""

    extent: tuple[float, float, float] = (60.0, 60.0, 30.0)  # metres along x, y, z
    ground_clearance: float = 0.5  # metres from the ground to the grid's lowest face
    inset: float = 0.2  # fraction of a voxel by which walls and roofs are set in
    core: float = 0.25  # the FREE rule's core (jaxmripp.runtime.depth); must be >= inset

    def __post_init__(self):
        if not 0.0 <= self.inset <= self.core < 0.5:
            raise ValueError(f"city frame: inset {self.inset} and core {self.core}; allowed: "
                             "0 <= inset <= core < 0.5 (FREE voxels must not hold a wall)")
        if self.ground_clearance <= 0:
            raise ValueError(f"city frame ground_clearance: got {self.ground_clearance}; "
                             "allowed: > 0 metres (the grid's lowest layer must be air)")

    @property
    def grid(self) -> GridFrame:
        return GridFrame(origin=(0.0, 0.0, self.ground_clearance), extent=self.extent,
                         core=self.core)


@dataclasses.dataclass(frozen=True)
class City:
    """One city in metres. Boxes: centre (B, 3) and half extents (B, 3); windows: one row
    per visible face, with the index of its window (W faces over T windows)."""

    size: int  # G
    frame: CityFrame
    height: np.ndarray  # (G, G) int building height in voxels
    box_centre: np.ndarray  # (B, 3) metres
    box_half: np.ndarray  # (B, 3) metres
    window_voxel: np.ndarray  # (T, 3) int
    face_point: np.ndarray  # (W, 3) metres, on a wall
    face_normal: np.ndarray  # (W, 3) unit outward normal
    face_window: np.ndarray  # (W,) int index into window_voxel

    @property
    def n_windows(self) -> int:
        return len(self.window_voxel)

    @property
    def voxel_metres(self) -> np.ndarray:
        return np.asarray(self.frame.extent) / self.size


def from_height_map(height: np.ndarray, window_voxel: np.ndarray,
                    frame: CityFrame = CityFrame()) -> "City":
    """A city from a (G, G) height map of rectangular blocks and (T, 3) window voxels."""
    from scipy import ndimage

    height = np.asarray(height, np.int64)
    size = height.shape[0]
    labels, count = ndimage.label(height > 0)
    voxel = np.asarray(frame.extent) / size
    lift = np.array([0.0, 0.0, frame.ground_clearance])
    lo_list, hi_list = [], []
    for block in ndimage.find_objects(labels):
        tops = height[block]
        if np.any(tops != tops.flat[0]):
            raise ValueError("city: a building block with more than one height; "
                             "world.clearance >= 1 keeps buildings apart")
        lo = np.array([block[0].start, block[1].start, 0]) * voxel + lift + frame.inset * voxel
        hi = np.array([block[0].stop, block[1].stop, tops.flat[0]]) * voxel + lift \
            - frame.inset * voxel
        lo[2] = 0.0  # down to the ground
        lo_list.append(lo)
        hi_list.append(hi)
    lo, hi = np.array(lo_list).reshape(-1, 3), np.array(hi_list).reshape(-1, 3)
    window_voxel = np.asarray(window_voxel, np.int64).reshape(-1, 3)
    points, normals, owner = _faces(height, window_voxel, frame, lift, voxel)
    hidden = np.setdiff1d(np.arange(len(window_voxel)), owner)
    if len(hidden):
        raise ValueError(f"city: window voxel {window_voxel[hidden[0]].tolist()} has no face "
                         "on the outside of its building (flight cities need "
                         "world.target_placement=facade)")
    return City(size, frame, height, (lo + hi) / 2, (hi - lo) / 2, window_voxel, points,
                normals, owner)


def _faces(height, window_voxel, frame: CityFrame, lift, voxel):
    """Every face of a window voxel whose neighbour is air (its column is lower), placed
    on the set-in wall, with its outward normal."""
    size = height.shape[0]
    points, normals, owner = [], [], []
    for index, (x, y, z) in enumerate(window_voxel):
        centre = (np.array([x, y, z]) + 0.5) * voxel + lift
        for axis in (0, 1):
            for sign in (-1, 1):
                n = [x, y]
                n[axis] += sign
                outside = not (0 <= n[0] < size and 0 <= n[1] < size) \
                    or height[n[0], n[1]] <= z
                if outside:
                    normal = np.zeros(3)
                    normal[axis] = sign
                    point = centre + normal * (0.5 - frame.inset) * voxel[axis]
                    points.append(point)
                    normals.append(normal)
                    owner.append(index)
    return (np.array(points).reshape(-1, 3), np.array(normals).reshape(-1, 3),
            np.array(owner, np.int64))


def generate(seed: int, world_cfg, frame: CityFrame = CityFrame()) -> City:
    """The city of `jaxmripp.sim.world.generate(jax.random.key(seed), world_cfg)` (the key
    `python -m jaxmripp.demo --seed` uses)."""
    import jax

    from jaxmripp.sim import world as worldmod

    world = jax.jit(worldmod.generate, static_argnums=1)(jax.random.key(seed), world_cfg)
    valid = np.asarray(world.target_valid)
    return from_height_map(np.asarray(world.height), np.asarray(world.target_voxel)[valid],
                           frame)
