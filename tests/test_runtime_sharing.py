"""Shared maps and the view gain in the NumPy runtime: building tops, the view-gain features
(`jaxmripp.spec.view`), the map message of protocol 3 and the delta bookkeeping
(`jaxmripp.spec.sharing`), and the order of the map round in `OnboardPlanner`.

References are written from the spec's text: tops from a map's OCCUPIED voxels and the
gain by walking each ray of the spec's table sample by sample (tests/gain_reference.py),
the merge as a whole-map merge. The JAX implementations (`jaxmripp.sim.view`) are
compared too, since the two sides must agree bit for bit. Whole episodes against the env
(maps, tops and features every round, with the runtime's deltas) are in
tests/test_runtime_episode.py and tests/test_runtime_parity.py.
"""

from __future__ import annotations

import base64
import copy
import dataclasses
import json
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import export
from jaxmripp.config import SensorConfig
from jaxmripp.runtime import (MessageError, OnboardPlanner, PlannerStateError,
                              ProtocolVersionError, WeightsFormatError, messages, view)
from jaxmripp.runtime.mapping import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from jaxmripp.runtime.sharing import MapSharing
from jaxmripp.sim import tops as jax_tops
from jaxmripp.sim import view as jax_view
from jaxmripp.spec import view as spec
from gain_reference import brute_tops, reference_gain
from test_runtime import CFG, spec_of

F32 = np.float32
G = 20
SENSOR = SensorConfig()
# The reference's frustum (sees through buildings) with windows inside footprints.
SEE_THROUGH = SensorConfig(gain_occlusion=False, gain_facade="column")


def model_of(sensor: SensorConfig) -> view.GainModel:
    return view.GainModel(sensor.fov_deg, sensor.range, sensor.gain_occlusion,
                          sensor.gain_facade)


MODEL = model_of(SENSOR)


def random_map(rng, size=G, p_occupied=0.1, p_unknown=0.4):
    codes = rng.choice(np.int8([FREE, UNKNOWN, OCCUPIED]), size=(size,) * 3,
                       p=[1 - p_occupied - p_unknown, p_unknown, p_occupied]).astype(np.int8)
    return codes


# ---------------------------------------------------------------------------------------
# Building tops and the view gain


def test_tops_follow_every_write_and_equal_the_occupied_voxels_and_jax():
    rng = np.random.default_rng(0)
    truth = random_map(rng, p_unknown=0.0, p_occupied=0.2).reshape(-1)
    ours = OccupancyMap(G)
    theirs = jnp.zeros((G, G), jnp.int8)
    raise_tops = jax.jit(jax_tops.raise_tops)
    for k in range(12):
        flat = rng.integers(0, G ** 3, 400)
        flat[:5] = flat[5:10]  # the same voxel written twice in one call
        if k % 3 == 2:  # a merge: codes taken only where unknown, tops from all OCCUPIED
            ours.merge(flat, truth[flat])
        else:
            ours.update(flat, truth[flat])
        theirs = raise_tops(theirs, jnp.asarray(flat, jnp.int32), jnp.asarray(truth[flat]))
        voxel = np.unravel_index(rng.integers(0, G ** 3), (G,) * 3)
        ours.mark_occupied(np.asarray(voxel))  # a blocked flight's voxel ahead
        theirs = raise_tops(theirs, jnp.int32([np.ravel_multi_index(voxel, (G,) * 3)]),
                            jnp.int8([OCCUPIED]))
        truth[np.ravel_multi_index(voxel, (G,) * 3)] = OCCUPIED
        np.testing.assert_array_equal(ours.top, brute_tops(ours.grid))
        np.testing.assert_array_equal(ours.top, np.asarray(theirs))
    assert ours.top.max() > 0


def test_view_gain_equals_the_jax_one_and_the_written_rule():
    rng = np.random.default_rng(1)
    gain = jax.jit(jax_view.view_gain, static_argnums=(3, 4))
    peers = jax.jit(jax_view.peer_distance, static_argnums=3)
    costs = jax.jit(jax_view.per_cost, static_argnums=2)
    around = SensorConfig(gain_facade="around")
    for trial in range(10):
        sensor = SEE_THROUGH if trial in (6, 7) else around if trial >= 8 else SENSOR
        grid = random_map(rng, p_occupied=0.05 * (trial % 3 + trial // 6),
                          p_unknown=0.3 + 0.1 * (trial % 6))
        # Tops from the map, or arbitrary ones (the gain reads whatever tops it is given).
        top = brute_tops(grid) if trial % 2 else rng.integers(0, G + 1, (G, G)).astype(np.int8)
        position = rng.random((12, 3)).astype(F32)
        position[:3] = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.99, 0.02, 0.5]]  # at the border
        want_unknown, want_facade = (np.asarray(x).reshape(-1) for x in gain(
            jnp.asarray(grid), jnp.asarray(top), jnp.asarray(position), sensor, G))
        poses, headings = np.repeat(position, 4, axis=0), np.tile(np.arange(4), 12)
        unknown, facade = view.view_gain(grid.reshape(-1), top, poses, headings,
                                         model_of(sensor), G)
        np.testing.assert_array_equal(unknown, want_unknown)
        np.testing.assert_array_equal(facade, want_facade)
        for k in range(0, 48, 5):
            np.testing.assert_allclose((unknown[k], facade[k]), reference_gain(
                grid, top, poses[k], headings[k], sensor), rtol=1e-6, atol=0)
        cost = rng.random(48).astype(F32) * F32(0.3)
        cost[:4] = 0.0  # padding turns in place
        np.testing.assert_array_equal(view.per_cost(unknown, cost, 0.21),
                                      np.asarray(costs(jnp.asarray(unknown), jnp.asarray(cost),
                                                       0.21)))
        others, heard = rng.random((4, 3)).astype(F32), rng.random(4) < 0.6
        np.testing.assert_array_equal(view.peer_distance(poses, others[heard], 0.21),
                                      np.asarray(peers(jnp.asarray(poses), jnp.asarray(others),
                                                       jnp.asarray(heard), 0.21)))


def test_view_gain_by_hand():
    centre = F32([0.5, 0.5, 0.5]) + F32(0.25 / G)  # voxel (10, 10, 10), far from the border
    empty = np.full((G, G, G), UNKNOWN, np.int8)
    no_tops = np.zeros((G, G), np.int8)

    def gain(grid, top, heading=0):
        u, f = view.view_gain(grid.reshape(-1), top, centre[None], np.int32([heading]),
                              MODEL, G)
        return float(u[0]), float(f[0])

    # Nothing known: everything in view is unknown, and no building is known.
    assert gain(empty, no_tops) == (1.0, 0.0)
    # A solid block ahead (x > 10): every sample lies in it, the first of each ray stops it.
    block = empty.copy()
    block[11:] = OCCUPIED
    assert gain(block, brute_tops(block)) == (0.0, 0.0)
    # One voxel right ahead: FREE, it is no longer unknown; OCCUPIED, it also hides every
    # sample behind it on the rays through it. Looking the other way, it changes nothing.
    ahead = np.ravel_multi_index((11, 10, 10), (G,) * 3)
    free, occupied = empty.copy(), empty.copy()
    free.reshape(-1)[ahead], occupied.reshape(-1)[ahead] = FREE, OCCUPIED
    assert gain(occupied, no_tops)[0] < gain(free, no_tops)[0] < 1.0
    assert gain(occupied, no_tops, heading=2) == gain(free, no_tops, heading=2) == (1.0, 0.0)
    offsets, weights = spec.gain_table(SENSOR.fov_deg, SENSOR.range, G)
    total = offsets.shape[1] * weights.sum()
    through = [r for r in range(offsets.shape[1]) if (offsets[0, r] == [1, 0, 0]).all(-1).any()]
    assert 1 <= len(through) < offsets.shape[1]  # the centre ray and maybe others
    lost_free = sum(weights[(offsets[0, r] == [1, 0, 0]).all(-1)].sum() for r in through)
    lost_occupied = sum(weights[np.argmax((offsets[0, r] == [1, 0, 0]).all(-1)):].sum()
                        for r in through)
    assert gain(free, no_tops)[0] == pytest.approx(1 - lost_free / total, abs=1e-7)
    assert gain(occupied, no_tops)[0] == pytest.approx(1 - lost_occupied / total, abs=1e-7)
    # A known roof at z = 14 in column (13, 10): unknown samples up to z = 15 in that
    # column and its four neighbours are facade, none elsewhere, none above.
    roof = empty.copy()
    roof[13, 10, 14] = OCCUPIED
    top = brute_tops(roof)
    assert top[13, 10] == 15 and top.sum() == 15
    unknown, facade = gain(roof, top)
    near = {(13, 10), (12, 10), (14, 10), (13, 9), (13, 11)}
    assert not (offsets[0] == [3, 0, 4]).all(-1).any()  # the roof hides no sample
    want = sum(w for ray in offsets[0] for (dx, dy, dz), w in zip(ray, weights)
               if (10 + dx, 10 + dy) in near and 10 + dz <= 15)
    assert want > 0 and facade == pytest.approx(want / total, abs=1e-7)
    assert facade < unknown <= 1.0


# ---------------------------------------------------------------------------------------
# The map message


def some_delta(rng, receiver, count=300):
    voxels = np.sort(rng.choice(G ** 3, count, replace=False))
    return messages.MapDelta(receiver, voxels, rng.random(count) < 0.3)


def test_map_message_round_trip_and_size():
    rng = np.random.default_rng(2)
    message = messages.MapMessage(1, G, (some_delta(rng, 0), some_delta(rng, 2, 0),
                                         some_delta(rng, 3, G ** 3)))
    data = messages.encode_map(message)
    back = messages.decode_map(data, G)
    assert (back.sender, back.size, back.protocol) == (1, G, messages.PROTOCOL_VERSION)
    for ours, theirs in zip(back.deltas, message.deltas):
        assert ours.receiver == theirs.receiver
        np.testing.assert_array_equal(ours.voxels, theirs.voxels)
        np.testing.assert_array_equal(ours.occupied, theirs.occupied)
    assert back.delta_for(2).voxels.size == 0 and back.delta_for(7) is None
    # Unsorted voxels are sent in flat order, each with its own code.
    shuffled = rng.permutation(300)
    delta = message.deltas[0]
    again = messages.decode_map(messages.encode_map(messages.MapMessage(1, G, (
        messages.MapDelta(0, delta.voxels[shuffled], delta.occupied[shuffled]),))), G)
    np.testing.assert_array_equal(again.deltas[0].occupied, delta.occupied)
    # A small delta costs far less than its raw mask (G^3 / 8 bytes).
    small = messages.encode_map(messages.MapMessage(1, G, (some_delta(rng, 0, 20),)))
    assert len(small) < 250 < G ** 3 // 8


def test_malformed_or_other_version_map_messages_are_refused_and_change_nothing():
    spec = spec_of()
    planners = [OnboardPlanner(spec, i, budget=1.0, team_size=3) for i in range(2)]
    g = spec.size
    for i, p in enumerate(planners):
        flat = np.arange(i, g ** 3, 7)
        p.sense(F32([0.5, 0.5, 0.3 + 0.1 * i]), 1, flat, (flat % 5 == 0).astype(np.int8) * 2, 0)
    a, b = planners
    b.receive(a.message())
    a.receive(b.message())
    record = json.loads(a.map_message())
    b.map_message()
    count = record["deltas"][0]["count"]
    assert count % 8  # the occupied mask has padding bits
    snapshot = (b.map.codes.copy(), b.map.top.copy(), b.sharing.learned.copy())

    def entry(**changes):
        return dict(record, deltas=[dict(record["deltas"][0], **changes)])

    packed = lambda raw: base64.b64encode(zlib.compress(raw)).decode()  # noqa: E731
    mask = zlib.decompress(base64.b64decode(record["deltas"][0]["voxels"]))
    mask_bytes = (g ** 3 + 7) // 8
    bad = {
        "not base64": entry(voxels="***"),
        "not zlib": entry(voxels=base64.b64encode(b"plain bytes").decode()),
        "short mask": entry(voxels=packed(bytes(mask_bytes - 1))),
        "long mask": entry(voxels=packed(bytes(mask_bytes + 1))),
        "bomb": entry(voxels=packed(bytes(50 * mask_bytes))),
        "corrupt": entry(voxels=record["deltas"][0]["voxels"][:-8] + "AAAAAAAA"),
        "trailing data": entry(voxels=base64.b64encode(zlib.compress(mask) + b"\0").decode()),
        "count": entry(count=count + 1),
        "padding": entry(occupied=packed(b"\xff" * ((count + 7) // 8))),
        "receiver twice": dict(record, deltas=record["deltas"] * 2),
        "receiver": entry(receiver=-1),
        "size": dict(record, size=g + 1),
        "deltas": dict(record, deltas={"1": 2}),
        "sender": dict(record, sender=5),
        "type": dict(record, type="jaxmripp.waypoints"),
    }
    for name, data in bad.items():
        with pytest.raises(MessageError) as err:
            b.receive_map(json.dumps(data))
        assert "\n" not in str(err.value), name
    for version in (4, 6):
        with pytest.raises(ProtocolVersionError, match=f"protocol {version}; this runtime "
                                                       "speaks protocol 5 only"):
            b.receive_map(json.dumps(dict(record, protocol=version)))
    with pytest.raises(MessageError):  # a waypoint message is no map message, and back
        b.receive_map(a.message())
    with pytest.raises(MessageError):
        b.receive(json.dumps(record))
    after = (b.map.codes, b.map.top, b.sharing.learned)
    for x, y in zip(after, snapshot):
        np.testing.assert_array_equal(x, y)
    b.receive_map(json.dumps(record))  # the message itself is fine
    assert (b.map.codes != UNKNOWN).sum() > (snapshot[0] != UNKNOWN).sum()


# ---------------------------------------------------------------------------------------
# Deltas against the whole-map merge of the spec


def test_deltas_give_the_whole_map_merge_under_changing_contacts():
    """Five robots sense parts of one world for 12 rounds under random contacts. Every
    round the runtime's maps and tops, after merging deltas, equal the spec's merge of
    whole maps (each robot takes, where UNKNOWN, the codes its neighbours held after their
    own sensing), and after a pair's first contact deltas are smaller than whole maps."""
    rng = np.random.default_rng(3)
    n, rounds = 5, 12
    truth = random_map(rng, p_unknown=0.0, p_occupied=0.15).reshape(-1)
    maps = [OccupancyMap(G) for _ in range(n)]
    books = [MapSharing(i, m) for i, m in enumerate(maps)]
    reference = np.full((n, G ** 3), UNKNOWN, np.int8)
    ratios = []
    for t in range(rounds):
        for i in range(n):
            flat = rng.integers(0, G ** 3, 600)
            maps[i].update(flat, truth[flat])
            books[i].note_sensed(t)
            reference[i, flat] = truth[flat]
        contact = np.triu(rng.random((n, n)) < 0.4, 1)
        contact = contact | contact.T
        outbox = [books[j].message(np.nonzero(contact[j])[0], t) for j in range(n)]
        sent = reference.copy()
        for i, j in zip(*np.nonzero(contact)):
            delta = outbox[j].delta_for(i)
            ratios.append((t, j, i, len(delta.voxels), int((maps[j].codes != UNKNOWN).sum())))
            books[i].merge(delta, j, t)
            reference[i] = np.where(reference[i] == UNKNOWN, sent[j], reference[i])
        for i in range(n):
            np.testing.assert_array_equal(maps[i].codes, reference[i], err_msg=f"round {t}")
            np.testing.assert_array_equal(maps[i].top, brute_tops(reference[i].reshape((G,) * 3)))
    # (The known count is taken after the merges of the round, so compare with a margin.)
    met, later = set(), []
    for t, j, i, size, known in ratios:
        if (j, i) in met:
            later.append(size / known)
        met.add((j, i))
    assert len(later) > 20 and max(later) < 1.0 and np.mean(later) < 0.6


# ---------------------------------------------------------------------------------------
# The planner's map round


def test_map_round_calls_out_of_order_are_refused():
    spec = spec_of()
    a, b = (OnboardPlanner(spec, i, budget=1.0, team_size=3) for i in range(2))
    for call in (a.map_message, lambda: a.receive_map(b"{}")):
        with pytest.raises(PlannerStateError, match="sense"):
            call()
    g = spec.size
    for p, z in ((a, 0.3), (b, 0.4)):
        p.sense(F32([0.5, 0.5, z]), 1, np.arange(g ** 3), np.zeros(g ** 3, np.int8), 0)
    b.receive(a.message())
    a.receive(b.message())
    from_a = a.map_message()
    with pytest.raises(PlannerStateError, match="map_message\\(\\) first"):
        b.receive_map(from_a)  # b has not sent its own yet
    with pytest.raises(PlannerStateError, match="already sent"):
        a.map_message()
    assert a.last_map_message_bytes == len(from_a)
    b.map_message()
    b.receive_map(from_a)
    assert b.receive_map(messages.MapMessage(b.id, g, ())) is None  # its own echo
    b.decide()
    for call in (b.map_message, lambda: b.receive_map(from_a)):
        with pytest.raises(PlannerStateError, match="before decide"):
            call()
    # Without shared maps there is no map round at all.
    quiet = OnboardPlanner(dataclasses.replace(spec, share_maps=False), 0, budget=1.0)
    quiet.sense(F32([0.5, 0.5, 0.5]), 1, np.zeros(0, np.int64), np.zeros(0, np.int8), 0)
    with pytest.raises(PlannerStateError, match="share_maps is false"):
        quiet.map_message()


def test_exports_without_share_maps_are_refused():
    header = json.loads(json.dumps(export.header(CFG)))
    old = copy.deepcopy(header)
    del old["config"]["radio"]["share_maps"]
    with pytest.raises(WeightsFormatError, match="config.radio.share_maps.*re-export"):
        type(spec_of()).from_header(old)
    header["config"]["radio"]["share_maps"] = "yes"
    with pytest.raises(WeightsFormatError, match="share_maps is not true/false"):
        type(spec_of()).from_header(header)
