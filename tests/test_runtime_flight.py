"""The safe-flight rules of `jaxmripp.spec.flight` in the NumPy runtime: the traversal of a
line of flight (`jaxmripp.runtime.mapping.traverse`), closest approach and the hold rule
(`jaxmripp.runtime.flight`), the take-off scan, the own voxel, the budget and intent of
the protocol and the intent round of `OnboardPlanner`.

References here are written independently of both implementations: an exact interval test
per voxel and dense sampling for the traversal, dense sampling in time for the closest
approach, and geometry worked by hand. The JAX implementations (`jaxmripp.sim.geometry`,
`jaxmripp.sim.flight`) are compared as well, since the two sides must agree."""

from __future__ import annotations

import dataclasses
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config, export
from jaxmripp.runtime import (Candidates, MessageError, OnboardPlanner, PlannerStateError,
                              ProtocolVersionError, RuntimeSpec, WeightsFormatError)
from jaxmripp.runtime import flight, messages, weights
from jaxmripp.runtime.spec import REMOVED
from jaxmripp.runtime.mapping import FREE, OCCUPIED, OccupancyMap, fly_until, traverse
from jaxmripp.sim import flight as jax_flight, geometry
from test_runtime import CFG, REPO, init_params

F32 = np.float32


def spec_of(cfg=CFG, **changes) -> RuntimeSpec:
    spec = export.runtime_spec(cfg)
    return dataclasses.replace(spec, **changes)


def visited(start, end, size, max_length=0.3) -> set:
    voxels, _ = traverse(np.asarray(start, F32), np.asarray(end, F32), size, max_length)
    return set(map(tuple, voxels.reshape(-1, 3).tolist()))


# ---------------------------------------------------------------------------------------
# Independent references for the traversal, in voxel units from the float32 start and end


def voxel_units(position, size) -> np.ndarray:
    """The spec's s = p G, computed in float32 as the rule says, then widened."""
    return (np.asarray(position, F32) * F32(size)).astype(np.float64)


def interval_reference(start, end, size) -> set:
    """Every voxel whose half-open cell (clipped into the grid) holds a point of the closed
    segment: per axis, the t where the coordinate lies in the cell is an interval, closed
    at the side the cell includes and open at the other; the voxel is traversed when the
    intersection of the three with [0, 1] is not empty. All voxels around the segment's
    bounding box are tested."""
    s, e = voxel_units(start, size), voxel_units(end, size)
    d = e - s
    lo = np.clip(np.floor(np.minimum(s, e)) - 1, 0, size - 1).astype(int)
    hi = np.clip(np.floor(np.maximum(s, e)) + 1, 0, size - 1).astype(int)
    v = np.stack(np.meshgrid(*(np.arange(a, b + 1) for a, b in zip(lo, hi)),
                             indexing="ij"), -1).reshape(-1, 3)
    floor_a = np.where(v == 0, -np.inf, v).astype(np.float64)  # cell [floor_a, ceil_a)
    ceil_a = np.where(v == size - 1, np.inf, v + 1).astype(np.float64)
    # Interval ends as (t, open?) pairs; the order "smaller t first, at equal t closed
    # before open" makes max / min of lower / upper ends the intersection's ends.
    low_t, low_open = np.zeros(len(v)), np.zeros(len(v), bool)
    high_t, high_open = np.ones(len(v)), np.zeros(len(v), bool)
    empty = np.zeros(len(v), bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in range(3):
            if d[a] == 0:
                empty |= ~((floor_a[:, a] <= s[a]) & (s[a] < ceil_a[:, a]))
                continue
            t_floor, t_ceil = (floor_a[:, a] - s[a]) / d[a], (ceil_a[:, a] - s[a]) / d[a]
            if d[a] > 0:  # t in [t_floor, t_ceil)
                lower, lower_open, upper, upper_open = t_floor, False, t_ceil, True
            else:  # t in (t_ceil, t_floor]
                lower, lower_open, upper, upper_open = t_ceil, True, t_floor, False
            later = (lower > low_t) | ((lower == low_t) & lower_open)
            low_t, low_open = np.where(later, lower, low_t), np.where(later, lower_open,
                                                                      low_open)
            sooner = (upper < high_t) | ((upper == high_t) & upper_open)
            high_t, high_open = np.where(sooner, upper, high_t), np.where(sooner, upper_open,
                                                                          high_open)
    inside = (low_t < high_t) | ((low_t == high_t) & ~low_open & ~high_open)
    return set(map(tuple, v[inside & ~empty].tolist()))


def sampled_reference(start, end, size, count=200_001) -> set:
    """Voxels of `count` evenly spaced points of the closed segment (both ends included)."""
    s, e = voxel_units(start, size), voxel_units(end, size)
    t = np.linspace(0.0, 1.0, count)[:, None]
    voxels = np.clip(np.floor(s + t * (e - s)), 0, size - 1).astype(int)
    flat = np.unique((voxels[:, 0] * size + voxels[:, 1]) * size + voxels[:, 2])
    return set(map(tuple, np.stack(np.unravel_index(flat, (size,) * 3), -1).tolist()))


def random_segments(rng, count, size, max_length):
    """Random segments of length <= max_length inside the unit cube, with a share of
    awkward ones: on voxel planes, axis-aligned, through grid corners, zero length."""
    starts, ends = [], []
    while len(starts) < count:
        kind = len(starts) % 4
        start = rng.random(3)
        offset = rng.normal(size=3)
        offset *= rng.random() * max_length / np.linalg.norm(offset)
        if kind == 1:  # start and end on quarter-voxel points: crossings tie exactly
            start = np.round(start * size * 4) / (4 * size)
            offset = np.round(offset * size * 4) / (4 * size)
        elif kind == 2:  # some axes not moving
            offset[rng.random(3) < 0.5] = 0.0
        elif kind == 3 and rng.random() < 0.2:
            offset[:] = 0.0
        end = start + offset
        if np.all((end >= 0) & (end <= 1)) and np.linalg.norm(offset) <= max_length:
            starts.append(start)
            ends.append(end)
    return np.asarray(starts, F32), np.asarray(ends, F32)


# ---------------------------------------------------------------------------------------
# Traversal


G = 10


# Hand-worked traversals in voxel units, G = 10 (tests/test_flight.py runs them on JAX too).
HAND_WORKED = [
    # A corner graze: the segment passes exactly through the corner (1, 1) of four cells
    # and visits the three cells that own its points.
    ((0.5, 1.5, 0.5), (1.5, 0.5, 0.5), {(0, 1, 0), (1, 1, 0), (1, 0, 0)}),
    # A diagonal through an edge: the point (1, 1) belongs to the cell (1, 1) only.
    ((0.5, 0.5, 0.5), (1.5, 1.5, 0.5), {(0, 0, 0), (1, 1, 0)}),
    # Along a face x = 1: the points lie in the cells with x index 1 only.
    ((1.0, 0.5, 0.5), (1.0, 3.5, 0.5), {(1, 0, 0), (1, 1, 0), (1, 2, 0), (1, 3, 0)}),
    # Zero length: its own voxel.
    ((2.5, 3.5, 4.5), (2.5, 3.5, 4.5), {(2, 3, 4)}),
    # From an integer coordinate moving down: the start point is in cell 3, then 2, 1.
    ((3.0, 0.5, 0.5), (1.5, 0.5, 0.5), {(3, 0, 0), (2, 0, 0), (1, 0, 0)}),
    # Moving down onto a plane: the end point x = 1 is in cell 1, not 0.
    ((2.5, 0.5, 0.5), (1.0, 0.5, 0.5), {(2, 0, 0), (1, 0, 0)}),
    # Along the world's top face (position 1.0): clipped into the last layer.
    ((0.5, 10.0, 0.5), (2.5, 10.0, 0.5), {(0, 9, 0), (1, 9, 0), (2, 9, 0)}),
]


@pytest.mark.parametrize("start, end, expected", HAND_WORKED)
def test_traversal_hand_worked_cases(start, end, expected):
    start, end = np.asarray(start) / G, np.asarray(end) / G
    assert visited(start, end, G) == expected
    assert interval_reference(start, end, G) == expected  # the reference agrees by hand


def test_traversal_equals_exact_and_dense_references_on_random_segments():
    rng = np.random.default_rng(0)
    starts, ends = random_segments(rng, 300, G, 0.21)
    for k, (start, end) in enumerate(zip(starts, ends)):
        got = visited(start, end, G, 0.21)
        assert got == interval_reference(start, end, G), (k, start * G, end * G)
        if k % 4 in (0, 2):  # no exact corner touches here: dense samples see every voxel
            assert got == sampled_reference(start, end, G), (k, start * G, end * G)


def test_traversal_is_vectorised_and_ignores_max_length_beyond_need():
    rng = np.random.default_rng(1)
    start = F32([0.43, 0.52, 0.47])
    ends = (start + (rng.random((50, 3)) - 0.5) * 0.4).astype(F32)
    voxels, entry = traverse(start, ends, G, 0.21)
    assert voxels.shape[:2] == entry.shape and voxels.shape[0] == 50
    for k, end in enumerate(ends):
        assert set(map(tuple, voxels[k].tolist())) == visited(start, end, G, 0.21)
    # A supplied segment longer than max_length still lists every voxel it enters.
    far = F32([0.95, 0.05, 0.93])
    assert visited(start, far, G, 0.05) == interval_reference(start, far, G)


# Compiled, XLA may contract a multiply into the subtraction after it (one rounding instead of
# two); the traversal materialises its scaled coordinates so that it does not, and the
# compiled env visits the spec's voxels as op-by-op JAX and the runtime do.
@pytest.mark.parametrize("compiled", [False, True])
def test_traversal_equals_jax_geometry_traverse(compiled):
    size, reach = 30, 0.21
    rng = np.random.default_rng(2)
    starts, ends = random_segments(rng, 400, size, reach)
    jax_traverse = jax.vmap(geometry.traverse, in_axes=(0, 0, None, None))
    if compiled:
        jax_traverse = jax.jit(jax_traverse, static_argnums=(2, 3))
    want_voxels, want_entry, complete = (
        np.asarray(x) for x in jax_traverse(jnp.asarray(starts), jnp.asarray(ends), size,
                                            reach))
    assert complete.all()

    def first_entry(v, t):
        out = {}
        for voxel, time in zip(map(tuple, v.tolist()), t.tolist()):
            out[voxel] = min(out.get(voxel, 2.0), time)
        return out

    sets = entries = 0
    for k in range(len(starts)):
        ours = first_entry(*traverse(starts[k], ends[k], size, reach))
        theirs = first_entry(want_voxels[k], want_entry[k])
        sets += set(ours) != set(theirs)
        entries += ours != theirs
    assert (sets, entries) == (0, 0), f"of {len(starts)} segments, {sets} voxel sets and " \
        f"{entries} entry times differ"


def test_known_free_needs_every_traversed_voxel_free_and_fly_until_stops_before():
    size = 10
    occupancy = OccupancyMap(size)
    occupancy.codes[:] = FREE
    start = F32([0.05, 0.15, 0.05])
    corner = F32([0.15, 0.05, 0.05])  # grazes the corner: (0,1,0), (1,1,0), (1,0,0)
    occupancy.grid[1, 1, 0] = 1  # UNKNOWN where only the corner point passes
    assert not occupancy.known_free(start, corner[None], 0.21)[0]
    occupancy.grid[1, 1, 0] = FREE
    assert occupancy.known_free(start, corner[None], 0.21)[0]
    occupancy.grid[4, 1, 0] = OCCUPIED
    far = F32([0.55, 0.15, 0.05])
    assert list(occupancy.known_free(start, np.stack([corner, far]), 0.21)) == [True, False]
    # Flying towards the occupied voxel stops midway through the last free piece (x in
    # [3, 4) entered at t = 2.5 / 5, the blocked voxel at t = 3.5 / 5).
    blocking = occupancy.codes == OCCUPIED
    stop, hit, voxel = fly_until(start, far, blocking, size, 0.6)
    assert hit and tuple(voxel) == (4, 1, 0)
    np.testing.assert_allclose(stop, [0.35, 0.15, 0.05], atol=1e-6)
    table = jnp.asarray(blocking)
    want = geometry.fly_until(jnp.asarray(start), jnp.asarray(far),
                              lambda v: table[geometry.linear_index(v, size)], size, 0.6)
    np.testing.assert_array_equal(stop, np.asarray(want[0]))
    assert bool(want[1]) and tuple(np.asarray(want[3])) == (4, 1, 0)
    assert fly_until(start, corner, blocking, size, 0.6)[1] is False


# ---------------------------------------------------------------------------------------
# Closest approach


def sampled_approach(a0, a1, b0, b1, count=400_001) -> float:
    """Dense in time: both fly at unit speed and hover at their ends."""
    a0, a1, b0, b1 = (np.asarray(x, np.float64) for x in (a0, a1, b0, b1))
    la, lb = np.linalg.norm(a1 - a0), np.linalg.norm(b1 - b0)
    t = np.linspace(0.0, max(la, lb), count)[:, None]
    at = a0 + (a1 - a0) * (np.minimum(t, la) / la if la else 0.0)
    bt = b0 + (b1 - b0) * (np.minimum(t, lb) / lb if lb else 0.0)
    return float(np.min(np.linalg.norm(at - bt, axis=-1)))


P = lambda *x: F32(x)  # noqa: E731


@pytest.mark.parametrize("a0, a1, b0, b1, gap", [
    # Swapping places: they meet halfway.
    (P(.2, .5, .5), P(.4, .5, .5), P(.4, .5, .5), P(.2, .5, .5), 0.0),
    # Crossing at right angles, reaching the crossing together.
    (P(.3, .5, .5), P(.5, .5, .5), P(.4, .4, .5), P(.4, .6, .5), 0.0),
    # The same paths, b starting 0.05 further back: relative position (t - .1, .15 - t)
    # is smallest at t = 0.125, where both components are 0.025.
    (P(.3, .5, .5), P(.5, .5, .5), P(.4, .35, .5), P(.4, .6, .5), 0.025 * math.sqrt(2)),
    # Flying through a hovering robot.
    (P(.3, .5, .5), P(.5, .5, .5), P(.4, .5, .5), P(.4, .5, .5), 0.0),
    # Parallel flights 0.1 apart.
    (P(.3, .5, .5), P(.5, .5, .5), P(.3, .6, .5), P(.5, .6, .5), 0.1),
    # a arrives early (length 0.05) and hovers at (.4, .53) while b passes below it at
    # t = 0.2: 0.03 then, more than 0.15 while a was still flying.
    (P(.4, .48, .5), P(.4, .53, .5), P(.2, .5, .5), P(.6, .5, .5), 0.03),
    # Both hovering: their distance.
    (P(.1, .1, .1), P(.1, .1, .1), P(.1, .4, .5), P(.1, .4, .5), 0.5),
])
def test_closest_approach_hand_worked(a0, a1, b0, b1, gap):
    assert float(flight.closest_approach(a0, a1, b0, b1)) == pytest.approx(gap, abs=1e-6)
    assert float(flight.closest_approach(b0, b1, a0, a1)) == pytest.approx(gap, abs=1e-6)
    assert sampled_approach(a0, a1, b0, b1) == pytest.approx(gap, abs=1e-5)


def test_closest_approach_equals_sampling_and_jax_on_random_flights():
    rng = np.random.default_rng(3)
    n = 200
    a0, b0 = rng.random((n, 3)).astype(F32), rng.random((n, 3)).astype(F32)
    a1 = (a0 + (rng.random((n, 3)) - 0.5) * 0.4).astype(F32)
    b1 = (b0 + (rng.random((n, 3)) - 0.5) * 0.4).astype(F32)
    b1[::7] = b0[::7]  # some hover
    b0[::5] = a0[::5] + F32(0.03)  # some start close
    ours = flight.closest_approach(a0, a1, b0, b1)
    assert ours.dtype == F32 and ours.shape == (n,)
    want = np.asarray(jax.jit(jax_flight.closest_approach)(a0, a1, b0, b1))
    np.testing.assert_array_equal(ours, want)  # one rule, the same bits (spec.vectors)
    # Inside a larger fusion too: the candidates' rule, vmapped over flights.
    fused = jax.jit(jax.vmap(lambda *v: jax_flight.closest_approach(*v)[0]))(
        *(x[:, None] for x in (a0, a1, b0, b1)))
    np.testing.assert_array_equal(ours, np.asarray(fused))
    for k in range(0, n, 5):
        assert ours[k] == pytest.approx(sampled_approach(a0[k], a1[k], b0[k], b1[k]),
                                        abs=1e-5)


def test_clear_of_robots_judges_the_whole_flight_and_equals_jax():
    start = F32([0.3, 0.5, 0.5])
    ends = F32([[0.5, 0.5, 0.5], [0.3, 0.7, 0.5], [0.3, 0.5, 0.5], [0.5, 0.56, 0.5]])
    others = F32([[0.4, 0.5, 0.5], [0.9, 0.9, 0.9]])  # one sits on the first flight's path
    # flight 0 passes through it; 1 goes away (0.1 at the start); 2 turns in place (0.1
    # away); 3 passes it 0.028 off the line, within d_c.
    got = flight.clear_of_robots(start, ends, others, 0.05)
    np.testing.assert_array_equal(got, [False, True, True, False])
    want = jax_flight.clear_of_robots(jnp.asarray(start), jnp.asarray(ends), jnp.asarray(others),
                                      jnp.ones(2, bool), jnp.float32(0.05))
    np.testing.assert_array_equal(got, np.asarray(want))
    assert flight.clear_of_robots(start, ends, np.zeros((0, 3)), 0.05).all()


def test_escape_lets_robots_within_d_c_part_and_equals_jax():
    """safety.escape: a robot 0.03 from another it hears (closer than d_c) may turn in
    place or fly what takes it no closer to it, but never through a third robot."""
    start = F32([0.5, 0.5, 0.5])
    others = F32([[0.53, 0.5, 0.5], [0.3, 0.5, 0.5]])  # one close by, one on the way out
    ends = F32([[0.7, 0.5, 0.5],   # towards the close one: no
                [0.5, 0.5, 0.5],   # turning in place: yes
                [0.5, 0.7, 0.5],   # sideways, at right angles: yes
                [0.4, 0.6, 0.5],   # away: yes
                [0.3, 0.5, 0.5]])  # away, into the second robot: no
    np.testing.assert_array_equal(flight.clear_of_robots(start, ends, others, 0.05), False)
    got = flight.clear_of_robots(start, ends, others, 0.05, escape=True)
    np.testing.assert_array_equal(got, [False, True, True, True, False])
    # Random flights near random robots, half of them within d_c: the two sides agree.
    rng = np.random.default_rng(3)
    starts = rng.uniform(0.3, 0.7, (400, 3)).astype(F32)
    near = starts + rng.normal(0, 0.03, (400, 3)).astype(F32)
    ends = np.clip(starts + rng.normal(0, 0.12, (400, 3)), 0, 1).astype(F32)
    jax_clear = jax.jit(jax.vmap(lambda s, e, o: jax_flight.clear_of_robots(
        s, e[None], o[None], jnp.ones(1, bool), jnp.float32(0.05), True)[0]))
    want = np.asarray(jax_clear(starts, ends, near))
    got = np.array([flight.clear_of_robots(s, e[None], o[None], 0.05, escape=True)[0]
                    for s, e, o in zip(starts, ends, near)])
    np.testing.assert_array_equal(got, want)
    close = np.linalg.norm(starts - near, axis=1) <= 0.05
    assert close.sum() > 100 and 0 < got[close].sum() < close.sum()


# ---------------------------------------------------------------------------------------
# Budget and intent in the protocol (from version 2 on)


def test_messages_round_trip_budget_and_intent_exactly():
    message = messages.Message(
        sender=1, position=F32([0.1, 0.2, 0.3]), heading=2, start=0,
        poses=F32([[0.1, 0.2, 0.3, math.pi]]), utilities=F32([0.25]),
        budget_left=F32(1 / 3), intent=F32([0.3, 0.2, 1 / 7]))
    back = messages.decode(messages.encode(message))
    assert back.protocol == messages.PROTOCOL_VERSION == 5
    assert back.budget_left == F32(1 / 3) and back.budget_left.dtype == F32
    np.testing.assert_array_equal(back.intent, message.intent)
    hover = messages.decode(messages.encode(dataclasses.replace(message, intent=None)))
    assert hover.intent is None
    assert json.loads(messages.encode(dataclasses.replace(message, intent=None)))["intent"] \
        is None


def test_older_version_messages_get_one_clear_error():
    record = json.loads(messages.encode(messages.Message(
        1, F32([0.1, 0.2, 0.3]), 0, 0, np.zeros((0, 4), F32), np.zeros(0, F32), F32(1.0))))
    version_1 = {k: v for k, v in record.items() if k not in ("budget_left", "intent", "seq")}
    version_3 = {k: v for k, v in record.items() if k != "seq"}
    for old in (dict(version_1, protocol=1), dict(version_3, protocol=2),
                dict(version_3, protocol=3), dict(record, protocol=4)):
        with pytest.raises(ProtocolVersionError, match=f"uses protocol {old['protocol']}; "
                           "this runtime speaks protocol 5 only") as err:
            messages.decode(json.dumps(old))
        assert "\n" not in str(err.value)
    bad = [dict(record, budget_left=-1.0), dict(record, budget_left="x"),
           {k: v for k, v in record.items() if k != "budget_left"},
           {k: v for k, v in record.items() if k != "intent"},
           dict(record, intent=[0.1, 0.2]), dict(record, intent=[0.1, 0.2, 1.5])]
    for data in bad:
        with pytest.raises(MessageError):
            messages.decode(json.dumps(data))


# ---------------------------------------------------------------------------------------
# The planner: export, take-off scan, own voxel, blocked moves, intents


def sense(planner, position, heading=1, n_seen=0, voxels=None, values=None):
    """Senses with every voxel of the world FREE unless voxels / values are given."""
    g = planner.spec.size
    if voxels is None:
        voxels, values = np.arange(g ** 3), np.zeros(g ** 3, np.int8)
    planner.sense(F32(position), heading, voxels, values, n_seen)


def test_export_header_carries_safety_and_other_flight_modes_and_removed_settings_are_refused(
        tmp_path):
    spec = spec_of()
    assert spec.flight == CFG.safety.flight
    header = export.header(CFG)
    assert header["config"]["safety"] == dataclasses.asdict(CFG.safety)
    assert header["config"]["robots"]["pad_spacing"] == CFG.robots.pad_spacing
    assert not spec.escape
    assert spec_of(config.load(REPO / "tests/smoke.yaml", ["safety.escape=true"])).escape
    without = export.header(CFG)
    del without["config"]["safety"]["escape"]  # optional: absent means off
    assert not RuntimeSpec.from_header(json.loads(json.dumps(without))).escape
    _, params = init_params()
    export.export(CFG, params, tmp_path)
    head = json.loads((tmp_path / "policy.json").read_text())
    for flight_mode in ("truncate", "optimistic"):
        head["config"]["safety"]["flight"] = flight_mode
        (tmp_path / "policy.json").write_text(json.dumps(head))
        with pytest.raises(WeightsFormatError, match=f"config.safety.flight is "
                                                     f"'{flight_mode}'.*known_free only"):
            OnboardPlanner.load(tmp_path, robot_id=0, budget=1.0)
    head["config"]["safety"]["flight"] = "known_free"
    # The removed settings, as older exports hold them: refused at another value than the
    # one built in, read at that one.
    for (section, key), built_in in REMOVED.items():
        other = (not built_in if isinstance(built_in, bool) else "other"
                 if isinstance(built_in, str) else built_in + 1)
        head["config"][section][key] = other
        (tmp_path / "policy.json").write_text(json.dumps(head))
        with pytest.raises(WeightsFormatError, match=f"config.{section}.{key} is {other!r}, a "
                                                     f"removed setting; the runtime has only "
                                                     f"{built_in!r}"):
            OnboardPlanner.load(tmp_path, robot_id=0, budget=1.0)
        head["config"][section][key] = built_in
    head["config"]["radio"]["map_reach"] = "radio"
    (tmp_path / "policy.json").write_text(json.dumps(head))
    assert OnboardPlanner.load(tmp_path, robot_id=0, budget=1.0).spec.share_maps == \
        CFG.radio.share_maps
    del head["config"]["safety"]
    (tmp_path / "policy.json").write_text(json.dumps(head))
    with pytest.raises(WeightsFormatError, match="config.safety.*re-export"):
        weights.load(tmp_path)
    with pytest.raises(ValueError, match="known_free only"):
        OnboardPlanner(dataclasses.replace(spec, flight="optimistic"), 0, budget=1.0)


def test_the_first_sense_charges_nothing_and_the_next_the_flight():
    spec = spec_of()
    planner = OnboardPlanner(spec, 0, budget=1.0, team_size=3)
    sense(planner, (0.5, 0.5, 0.5))
    assert planner.budget_left == planner.budget_initial == F32(1.0)
    d = planner.decide()
    planner.resolve()
    sense(planner, d.position, d.heading)
    turn = F32(spec.turn_cost) * F32(d.heading != 1)
    assert planner.budget_left == pytest.approx(1.0 - np.linalg.norm(
        d.position - F32([0.5, 0.5, 0.5])) - turn, abs=1e-6)


def test_sense_marks_the_own_voxel_free_and_blocked_moves_map_the_voxel_ahead():
    spec = spec_of()
    g = spec.size
    planner = OnboardPlanner(spec, 0, budget=1.0, team_size=3)
    own = (15, 15, 15)
    flat_own = np.ravel_multi_index(own, (g,) * 3)
    # The camera claims the own voxel occupied: the robot is there, so it is FREE.
    planner.sense(F32([0.51, 0.51, 0.51]), 0, np.array([flat_own]), np.array([OCCUPIED]), 0)
    assert planner.map.codes[flat_own] == FREE
    assert np.sum(planner.map.codes == FREE) == 1  # nothing else is known
    # A commanded flight along +x stopped at x = 17.5 / 30: the voxel ahead is (18, 15, 15),
    # the first one entered after the stop.
    sense(planner, (0.51, 0.51, 0.51), heading=0)
    target = F32([0.71, 0.51, 0.51])
    d = planner.decide(candidates=Candidates(target[None], np.int32([0]), None, None))
    assert not d.hover and planner.resolve() is d
    nothing = (np.zeros(0, np.int64), np.zeros(0, np.int8))
    planner.sense(F32([17.5 / 30, 0.51, 0.51]), 0, *nothing, 0, blocked=True)
    assert planner.map.grid[18, 15, 15] == OCCUPIED
    assert planner.map.grid[17, 15, 15] == FREE  # its own voxel now


def test_far_off_supplied_candidates_are_refused_as_outside_without_traversing():
    planner = OnboardPlanner(spec_of(), 0, budget=1.0, team_size=3)
    sense(planner, (0.5, 0.5, 0.5))
    far = Candidates(F32([[1e6, 0.5, 0.5], [0.5, 0.5, -5e3], [0.5, 0.5, 0.7]]),
                     np.int32([1, 1, 1]), None, None)
    d = planner.decide(candidates=far)
    np.testing.assert_array_equal(d.safe, [False, False, True])
    assert d.index == 2


def pair(spec, budgets=(1.0, 1.0)):
    """Robots 0 and 1 at (.4, .5, .5) and (.6, .5, .5), 0.2 apart (in radio range), both
    choosing to fly to (.5, .6, .5): each flight keeps 0.14 from the other robot where it
    hovers (the candidate rule passes), but the two flights arrive there together."""
    planners = [OnboardPlanner(spec, i, budget=b, team_size=3) for i, b in enumerate(budgets)]
    starts = [F32([0.4, 0.5, 0.5]), F32([0.6, 0.5, 0.5])]
    target = F32([0.5, 0.6, 0.5])
    for planner, start in zip(planners, starts):
        sense(planner, start, heading=1)
    return planners, starts, target


def round_of(planners, target, hear=True):
    """One full round (after sense) with every robot offered `target` only."""
    outbox = [p.message() for p in planners]
    if hear:
        planners[0].receive(outbox[1])
        planners[1].receive(outbox[0])
    decisions = [p.decide(candidates=Candidates(target[None], np.int32([1]), None, None))
                 for p in planners]
    assert not any(d.hover for d in decisions), [d.reason for d in decisions]
    intents = [p.intent_message() for p in planners]
    if hear:
        planners[0].receive_intent(intents[1])
        planners[1].receive_intent(intents[0])
    return [p.resolve() for p in planners]


@pytest.mark.parametrize("budgets", [(1.0, 1.0), (0.5, 1.0)])
def test_hold_rule_the_higher_id_holds(budgets):
    """The lower id goes first, whatever budget each robot has left."""
    holder = 1
    spec = spec_of()
    planners, starts, target = pair(spec, budgets)
    gap = flight.closest_approach(starts[0], target, starts[1], target)
    assert gap <= spec.collision_distance  # the two flights do conflict ...
    assert flight.clear_of_robots(starts[0], target[None], starts[1][None],
                                  spec.collision_distance)[0]  # ... the candidates do not
    decisions = round_of(planners, target)
    flier = 1 - holder
    assert not decisions[flier].hover and decisions[flier].yields_to is None
    held = decisions[holder]
    assert held.hover and held.index == -1 and held.yields_to == flier
    assert held.reason.startswith(f"hold: yields to robot {flier}")
    np.testing.assert_array_equal(held.position, starts[holder])
    # A hold is no move: the next sense at the same pose charges nothing, records no visit.
    before = (planners[holder].budget_left, len(planners[holder].history_pose))
    sense(planners[holder], starts[holder], heading=1)
    assert (planners[holder].budget_left, len(planners[holder].history_pose)) == before
    assert planners[holder].step == 1
    sense(planners[flier], target, heading=1)
    assert len(planners[flier].history_pose) == 2


def test_out_of_range_nobody_holds():
    planners, _, target = pair(spec_of())
    assert not any(d.hover for d in round_of(planners, target, hear=False))


def test_flights_apart_and_hovering_robots_do_not_cause_holds():
    spec = spec_of()
    planners, starts, _ = pair(spec)
    outbox = [p.message() for p in planners]
    planners[1].receive(outbox[0])
    away = [F32([0.4, 0.3, 0.5]), F32([0.6, 0.7, 0.5])]  # flights that separate
    d0 = planners[0].decide(candidates=Candidates(away[0][None], np.int32([1]), None, None))
    d1 = planners[1].decide(candidates=Candidates(away[1][None], np.int32([1]), None, None))
    planners[1].receive_intent(planners[0].intent_message())
    assert planners[1].resolve() is d1 and not d1.hover and not d0.hover
    # A robot that hovers announces no flight.
    planners[0]._pending = dataclasses.replace(d0, hover=True)
    assert messages.decode(planners[0].intent_message()).intent is None


def test_intent_calls_out_of_order_are_refused():
    planner = OnboardPlanner(spec_of(), 0, budget=1.0, team_size=3)
    sense(planner, (0.5, 0.5, 0.5))
    for call in (planner.intent_message, planner.resolve,
                 lambda: planner.receive_intent(planner.message())):
        with pytest.raises(PlannerStateError, match="decide"):
            call()
    planner.decide()
    message = messages.decode(planner.intent_message())
    assert message.start == len(planner.history_pose) and len(message.poses) == 0
    assert message.budget_left == planner.budget_left and message.intent is not None
    planner.resolve()
    with pytest.raises(PlannerStateError):
        planner.resolve()  # once per decision
