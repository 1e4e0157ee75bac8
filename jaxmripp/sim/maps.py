"""The team's maps in one array: per voxel, the truth and which robots know it.

A robot's map holds, per voxel, FREE, OCCUPIED or UNKNOWN (`jaxmripp.spec.grid`), and
what it holds is always the truth: casts and bumps write what is there, and merges copy
what peers wrote. So an environment keeps its N maps as bits: bit 0 of a voxel says
whether it is a building, bit 1 + i whether robot i knows it, packed into W =
`words(N)` bytes per voxel. A team map is (W, G, G, G) uint8; robot i's bit lives in word
(1 + i) // 8. Against N bytes per voxel for N int8 maps, this reads and writes a third of
the memory at N = 3 and lets a map merge update every robot's bits in place, one pass
over one byte per voxel.

The simulator's readers take a robot's view of the team map (`RobotMap`, `codes_at`):
one byte read per voxel, decoded for the robot, so no robot's map is ever written out.
`robot_maps` derives the int8 maps (N, G, G, G) whole, for planners, tests and pictures.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxmripp.sim import geometry, sensing
from jaxmripp.spec.grid import FREE, OCCUPIED, UNKNOWN

BUILDING = 1  # bit 0 of word 0


def words(n_robots: int) -> int:
    """W: bytes per voxel for the building bit and N robots' bits."""
    return (n_robots + 8) // 8


def _place(robot):
    """Robot indices (NumPy or JAX integers) -> (word, bit value as uint8) of their bits."""
    place = robot + 1
    return place // 8, (1 << (place % 8)).astype(np.uint8)


def _bit_places(n_robots: int) -> tuple[np.ndarray, np.ndarray]:
    """(word (N,), bit value (N,) uint8) of each robot's bit."""
    return _place(np.arange(n_robots))


def empty(height: jax.Array, n_robots: int) -> jax.Array:
    """A world's column heights (G, G) -> the team map (W, G, G, G) uint8 of a team that
    knows nothing yet: only the building bits set."""
    size = height.shape[0]
    solid = jnp.arange(size)[None, None, :] < height[:, :, None]
    truth = jnp.where(solid, jnp.uint8(BUILDING), jnp.uint8(0))
    rest = jnp.zeros((words(n_robots) - 1, size, size, size), jnp.uint8)
    return jnp.concatenate([truth[None], rest])


def robot_maps(team: jax.Array, n_robots: int) -> jax.Array:
    """(..., W, G, G, G) uint8 team maps -> (..., N, G, G, G) int8 robot maps (geometry
    codes)."""
    word, bit = _bit_places(n_robots)
    known = (team[..., word, :, :, :] & jnp.asarray(bit)[:, None, None, None]) != 0
    code = jnp.where(buildings(team)[..., None, :, :, :], jnp.int8(OCCUPIED), jnp.int8(FREE))
    return jnp.where(known, code, jnp.int8(UNKNOWN))


def buildings(team: jax.Array) -> jax.Array:
    """(..., W, G, G, G) team maps -> (..., G, G, G) bool the truth they hold: buildings."""
    return (team[..., 0, :, :, :] & BUILDING) != 0


def pack(robot_maps: jax.Array, building: jax.Array) -> jax.Array:
    """The inverse of `robot_maps`: (..., N, G, G, G) int8 robot maps that agree with the
    truth where they know a voxel, and the truth (..., G, G, G) bool (buildings) -> team
    maps (..., W, G, G, G) uint8. For building states to order (tests, pictures)."""
    n = robot_maps.shape[-4]
    word, bit = _bit_places(n)
    known = robot_maps != UNKNOWN
    packed = []
    for w in range(words(n)):
        byte = jnp.where(building, jnp.uint8(BUILDING), jnp.uint8(0)) if w == 0 else \
            jnp.zeros(building.shape, jnp.uint8)
        for i in np.flatnonzero(word == w):
            byte = byte | jnp.where(known[..., i, :, :, :], jnp.uint8(bit[i]), jnp.uint8(0))
        packed.append(byte)
    return jnp.stack(packed, axis=-4)


def codes_at(words: jax.Array, robot: jax.Array, cell: jax.Array) -> jax.Array:
    """Robots' codes from team-map words (W, C) uint8 (one map's G**3 cells, or several
    maps side by side) at cells (in [0, C)) and robots (broadcast with them): one byte
    read per voxel, two with W > 1."""
    count, cells = words.shape
    flat = words.reshape(-1)
    first = geometry.take_flat(flat, cell)
    word, bit = _place(jnp.asarray(robot, jnp.int32))
    own = first if count == 1 else geometry.take_flat(flat, word * cells + cell)
    known = (own & bit) != 0
    code = jnp.where((first & BUILDING) != 0, jnp.int8(OCCUPIED), jnp.int8(FREE))
    return jnp.where(known, code, jnp.int8(UNKNOWN))


@struct.dataclass
class RobotMap:
    """One robot's map as read from its team map (a `geometry.CodeReader`, taken by the
    map readers in place of an int8 map): its codes at flat voxel indices, one byte read
    each."""

    words: jax.Array  # (W, G**3) uint8 the team map
    robot: jax.Array  # () int32

    def codes(self, cell: jax.Array) -> jax.Array:
        return codes_at(self.words, self.robot, cell)


def robot_map(team: jax.Array, robot: jax.Array) -> RobotMap:
    """Robot `robot`'s map in the team map (W, G, G, G)."""
    return RobotMap(team.reshape(team.shape[0], -1), jnp.asarray(robot, jnp.int32))


def observe(team: jax.Array, voxels: jax.Array) -> jax.Array:
    """Team map, each robot's observed flat voxel indices (N, V) (outside [0, G**3): none)
    -> the team map with those voxels known to their robots.

    A robot's list must hold an in-grid voxel at most once, as a cast's does (its voxels
    are distinct offsets of the camera's view table). Robots' bits are distinct, so all
    robots' bits not yet set go in as one scatter-add: the sum of distinct bits is their
    union."""
    n, cells = voxels.shape[0], team[0].size
    word, bit = _bit_places(n)
    inside = (voxels >= 0) & (voxels < cells)
    index = jnp.where(inside, jnp.asarray(word, jnp.int32)[:, None] * cells + voxels, team.size)
    flat = team.reshape(-1)
    current = geometry.take_flat(flat, jnp.minimum(index, team.size - 1))
    bits = jnp.asarray(bit)[:, None]
    added = jnp.where((current & bits) == 0, bits, jnp.uint8(0))
    return sensing.scatter_add(flat, index.reshape(-1), added.reshape(-1)).reshape(team.shape)


def merge(team: jax.Array, linked: jax.Array) -> jax.Array:
    """Team map, (N, N) bool links (i hears j) -> every robot also knows what the robots it
    hears knew before the merge: the map merge of `jaxmripp.spec.sharing`.

    A robot's new bit is whether a robot it hears (or itself) has its bit set. With one
    word per voxel (N <= 7) that is one elementwise pass over the map, in place. Larger
    teams take one pass per distinct set of robots heard (`_merge_by_sets`), or, for a
    batch of small maps, one pass per robot across the batch (`_merge_by_receivers`)."""
    n, count = linked.shape[0], team.shape[0]
    if count > 1:
        return _merge_by_sets(team, linked)
    bit = _bit_places(n)[1]
    masks = _heard_bits(linked, count)
    return team | functools.reduce(jnp.bitwise_or, [
        jnp.where(_hears(team, masks[i]), jnp.uint8(bit[i]), jnp.uint8(0)) for i in range(n)])


def _bits_by_word(related: jax.Array, count: int) -> jax.Array:
    """(N, N) bool -> (N, W) uint8: per robot i and word, the bits of the robots j with
    related[i, j]."""
    word, bit = _bit_places(related.shape[0])
    in_word = np.arange(count)[None, :] == word[:, None]  # (N, W)
    # Distinct bits: their sum is their union.
    return jnp.sum(jnp.where(related[:, :, None] & in_word[None],
                             jnp.asarray(bit, jnp.int32)[None, :, None], 0),
                   axis=1).astype(jnp.uint8)


def _heard_bits(linked: jax.Array, count: int) -> jax.Array:
    """(N, N) links -> (N, W) uint8: per receiver and word, the bits of the robots it hears
    and its own."""
    return _bits_by_word(linked | jnp.eye(linked.shape[0], dtype=bool), count)


def _hears(team: jax.Array, heard: jax.Array) -> jax.Array:
    """(G, G, G) bool: a robot with heard bits (W,) hears of the voxel."""
    return jnp.any((team & heard[:, None, None, None]) != 0, axis=0)


def _set_bits(team: jax.Array, word: jax.Array, where: jax.Array, bits: jax.Array) -> jax.Array:
    """The team map with `bits` (uint8) set in word `word` where `where` (G, G, G) holds."""
    row = jax.lax.dynamic_index_in_dim(team, word, keepdims=False) \
        | jnp.where(where, bits, jnp.uint8(0))
    return jax.lax.dynamic_update_index_in_dim(team, row, word, 0)


@jax.custom_batching.custom_vmap
def _merge_by_sets(team: jax.Array, linked: jax.Array) -> jax.Array:
    """`merge` with W > 1 words: robots that hear the same set learn the same voxels (with
    relay or global radio a connected component is one set), so each distinct set takes
    one pass over the map, for all its robots at once, and a robot that hears nobody
    takes none. The passes are skipped by conditionals, so a batch of maps is merged map
    by map (a vmapped conditional would run every pass)."""
    n, count = linked.shape[0], team.shape[0]
    masks = _heard_bits(linked, count)
    same = jnp.all(masks[:, None, :] == masks[None, :, :], axis=-1)  # (N, N) equal sets
    first = ~jnp.any(same & np.tri(n, k=-1, dtype=bool), axis=1)  # lowest index of its set
    learns = first & jnp.any(linked & ~jnp.eye(n, dtype=bool), axis=1)
    members = _bits_by_word(same, count)  # per robot: the bits of the robots of its set

    def receive(i, merged):
        def learn(merged):
            new = _hears(team, masks[i])  # from the map before the merge

            def into_word(w, merged):
                return jax.lax.cond(members[i, w] != 0,
                                    lambda m: _set_bits(m, w, new, members[i, w]),
                                    lambda m: m, merged)

            return jax.lax.fori_loop(0, count, into_word, merged)

        return jax.lax.cond(learns[i], learn, lambda m: m, merged)

    return jax.lax.fori_loop(0, n, receive, team)


def _merge_by_receivers(team: jax.Array, linked: jax.Array) -> jax.Array:
    """`merge` with W > 1 words, receiver by receiver with no conditionals: each takes a
    pass, so a vmapped batch runs as one (the batch rule's choice for small maps)."""
    word, bit = _bit_places(linked.shape[0])
    masks = _heard_bits(linked, team.shape[0])

    def receive(i, merged):
        return _set_bits(merged, jnp.asarray(word, jnp.int32)[i], _hears(team, masks[i]),
                         jnp.asarray(bit)[i])

    return jax.lax.fori_loop(0, linked.shape[0], receive, team)


# Below this many voxels a map's passes cost less than stepping through a batch map by map
# (measured on 2-core CPUs). An accelerator runs a batch's passes in parallel and would run
# map by map one map at a time, so there a batch always merges receiver by receiver.
_MAP_BY_MAP_VOXELS = 400_000


@_merge_by_sets.def_vmap
def _merge_by_sets_vmap(axis_size, in_batched, team, linked):
    team, linked = [x if b else jnp.broadcast_to(x, (axis_size, *x.shape))
                    for x, b in zip((team, linked), in_batched)]
    if team[0, 0].size < _MAP_BY_MAP_VOXELS or jax.default_backend() != "cpu":
        return jax.vmap(_merge_by_receivers)(team, linked), True

    def one(e, merged):
        own = _merge_by_sets(jax.lax.dynamic_index_in_dim(merged, e, keepdims=False),
                             linked[e])
        return jax.lax.dynamic_update_index_in_dim(merged, own, e, 0)

    return jax.lax.fori_loop(0, axis_size, one, team), True
