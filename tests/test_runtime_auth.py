"""Authenticated team radio (`jaxmripp.runtime.auth`, protocol 4 of `jaxmripp.spec.protocol`)
and the map merge rule that no message can free a voxel (`jaxmripp.spec.sharing`).

The tag is recomputed here from the protocol's text with the standard library alone, not
through the runtime. Every refusal must raise `MessageError` with its reason, count it in
`rejected_messages` and leave the rest of the planner as it was (compared pickled).
"""

from __future__ import annotations

import base64
import copy
import hashlib
import hmac
import json
import pickle

import numpy as np
import pytest

from jaxmripp.runtime import (MessageError, OnboardPlanner, TeamKeyError, messages,
                              team_key)
from jaxmripp.runtime.auth import REASONS
from jaxmripp.runtime.mapping import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from jaxmripp.runtime.sharing import MapSharing
from test_runtime import sense_free, spec_of

F32 = np.float32
KEY = team_key(7)
SPEC = spec_of()
G = SPEC.size


def fingerprint(planner) -> bytes:
    """Everything a planner holds except its count of refused messages."""
    counts = planner.radio.rejected
    planner.radio.rejected = None
    try:
        return pickle.dumps(planner)
    finally:
        planner.radio.rejected = counts


def refused(planner, call, data, reason):
    """call(data) is refused for `reason`, counted once, and changes nothing else."""
    before, counts = fingerprint(planner), planner.rejected_messages
    with pytest.raises(MessageError) as err:
        call(data)
    assert err.value.reason == reason, str(err.value)
    assert "\n" not in str(err.value)
    counts[reason] += 1
    assert planner.rejected_messages == counts
    assert fingerprint(planner) == before
    return str(err.value)


def team(key=KEY, n=3, spec=SPEC):
    planners = [OnboardPlanner(spec, i, budget=1.0, team_size=n, team_key=key)
                for i in range(n)]
    for i, p in enumerate(planners):
        sense_free(p, position=(0.5, 0.3 + 0.2 * i, 0.5))
    return planners


def test_the_tag_is_the_hmac_the_protocol_writes_and_seq_counts_every_broadcast():
    a = team()[0]
    sent = [a.message()]
    sent.append(a.map_message())
    a.decide()
    sent.append(a.intent_message())
    for seq, data in enumerate(sent, start=1):
        # {"tag":"<44 base64 characters>",<rest>; signed bytes: "{" + rest.
        assert data.startswith(b'{"tag":"') and data[52:54] == b'",'
        signed = b"{" + data[54:]
        record = json.loads(data)
        assert list(record)[0] == "tag" and record["sender"] == 0 and record["seq"] == seq
        assert json.loads(signed) == {k: v for k, v in record.items() if k != "tag"}
        mac = hmac.new(KEY, b"jaxmripp.radio\x00" + (0).to_bytes(8, "big")
                       + seq.to_bytes(8, "big") + signed, hashlib.sha256).digest()
        assert data[8:52] == base64.b64encode(mac)
    # The same message unsigned: the tag member is the whole difference (53 bytes).
    plain = OnboardPlanner(SPEC, 0, budget=1.0, team_size=3)
    sense_free(plain, position=(0.5, 0.3, 0.5))
    assert len(sent[0]) - len(plain.message()) == len('"tag":"",') + 44 == 53


def test_a_keyed_team_refuses_unsigned_forged_altered_replayed_and_reordered_messages():
    a, b, _ = team()
    first, second = a.message(), a.message()
    assert b.receive(first).seq == 1
    heard = refused(b, b.receive, first, "stale")  # replayed
    assert "seq 1 was already taken" in heard
    other = copy.deepcopy(a)  # the same robot, its next two messages
    third, fourth = other.message(), other.message()
    assert b.receive(fourth).seq == 4
    for old in (second, third):  # out of order: older than one already taken
        refused(b, b.receive, old, "stale")

    outsider = OnboardPlanner(SPEC, 0, budget=1.0, team_size=3)  # no key: claims id 0
    sense_free(outsider)
    for _ in range(10):
        unsigned = outsider.message()
    assert "is not signed" in refused(b, b.receive, unsigned, "unsigned")
    wrong = OnboardPlanner(SPEC, 0, budget=1.0, team_size=3, team_key=team_key(8))
    sense_free(wrong)
    for _ in range(10):
        forged = wrong.message()
    assert "does not verify" in refused(b, b.receive, forged, "forged")
    fresh = other.message()  # seq 5, signed: altered in one digit of its position
    record = json.loads(fresh)
    spot = fresh.index(b'"position":[') + len(b'"position":[') + 2
    altered = fresh[:spot] + (b"1" if fresh[spot:spot + 1] != b"1" else b"2") \
        + fresh[spot + 1:]
    assert json.loads(altered)["position"] != record["position"]
    refused(b, b.receive, altered, "forged")
    moved = json.dumps(dict({k: v for k, v in record.items() if k != "tag"},
                            tag=record["tag"]), separators=(",", ":")).encode()
    assert "not the first member" in refused(b, b.receive, moved, "forged")
    refused(b, b.receive, messages.decode(fresh), "unsigned")  # an object has no tag
    assert b.receive(fresh).seq == 5  # the message itself is fine
    assert b.rejected_messages == {"malformed": 0, "version": 0, "unsigned": 2, "forged": 3,
                                   "stale": 3}


def test_without_a_key_messages_are_taken_as_before():
    a, b, _ = team(key=None)
    signed = team()[0].message()
    message = a.message()
    assert b"tag" not in message and json.loads(message)["seq"] == 1
    for data in (message, message, signed, a.message()):  # replays and tags unchecked
        assert b.receive(data).sender == 0
    assert b.rejected_messages == dict.fromkeys(REASONS, 0)


def test_team_keys_are_bytes_of_16_or_more():
    assert len(team_key()) == 32 and team_key() != team_key()  # the OS's random source
    assert team_key(3) == team_key(3) != team_key(4)  # simulated teams: from the seed
    for bad, shown in (("secret" * 4, "got str"), (b"short", "got 5 bytes"), (12, "got int")):
        with pytest.raises(TeamKeyError, match=f"team_key: {shown}; allowed: None or bytes "
                                               "of at least 16"):
            OnboardPlanner(SPEC, 0, budget=1.0, team_key=bad)
    OnboardPlanner(SPEC, 0, budget=1.0, team_key=bytearray(16))


def crowded_round(victim, attacker_key):
    """Robot 1 (`victim`) in the map round, then its decision, with a message claiming
    robot 0 in each broadcast: a map delta for robot 1 and an intent across its flight.
    Returns (decision after the intents, the map before the forged delta)."""
    forger = OnboardPlanner(SPEC, 0, budget=1.0, team_size=3, team_key=attacker_key)
    sense_free(forger, position=(0.5, 0.5, 0.2))
    victim.map_message()
    before = victim.map.codes.copy()
    # The forged delta: every voxel FREE, the ones robot 1 saw OCCUPIED among them.
    everything = messages.MapDelta(1, np.arange(G ** 3), np.zeros(G ** 3, bool))
    forger.radio.sequence = 100
    data = forger.radio.seal(messages.encode_map(messages.MapMessage(0, G, (everything,),
                                                                     seq=101)), 101)
    try:
        victim.receive_map(data)
    except MessageError:
        pass
    decision = victim.decide()
    assert not decision.hover
    # Robot 0 announces a flight through robot 1's target.
    intent = messages.encode(messages.Message(
        0, victim.position, 0, 0, np.zeros((0, 4), F32), np.zeros(0, F32), F32(1.0),
        intent=decision.position, seq=102))
    try:
        victim.receive_intent(forger.radio.seal(intent, 102))
    except MessageError:
        pass
    return victim.resolve(), before


def victim_robot(key):
    """Robot 1, having seen a slab of OCCUPIED voxels and the rest of its half FREE."""
    victim = OnboardPlanner(SPEC, 1, budget=1.0, team_size=3, team_key=key)
    flat = np.arange(G ** 3)
    x = flat // (G * G)
    seen = flat[x >= G // 2]
    codes = np.where(x[seen] == G - 1, OCCUPIED, FREE).astype(np.int8)
    victim.sense(F32([0.75, 0.5, 0.5]), 1, seen, codes, 0)
    return victim


@pytest.mark.parametrize("attacker_key", [None, team_key(99)], ids=["unsigned", "other_key"])
def test_a_forged_robot_0_neither_takes_priority_nor_changes_the_map(attacker_key):
    keyed = victim_robot(KEY)
    resolved, before = crowded_round(keyed, attacker_key)
    assert not resolved.hover and resolved.yields_to is None
    np.testing.assert_array_equal(keyed.map.codes, before)
    reason = "unsigned" if attacker_key is None else "forged"
    assert keyed.rejected_messages[reason] == 2
    # The same messages to a robot without a key: robot 0 goes first, and the
    # delta frees what robot 1 did not know (but none of what it saw OCCUPIED).
    open_radio = victim_robot(None)
    resolved, before = crowded_round(open_radio, None)
    assert resolved.hover and resolved.yields_to == 0
    after = open_radio.map.codes
    assert np.all(after[before == UNKNOWN] == FREE)
    np.testing.assert_array_equal(after[before != UNKNOWN], before[before != UNKNOWN])
    assert (before == OCCUPIED).sum() == G * G and open_radio.sharing.conflicts == G * G


# ---------------------------------------------------------------------------------------
# The merge rule


def test_no_message_frees_a_voxel_and_occupied_wins_over_free():
    """Every pair (code here, code in the delta) against the rule's table."""
    codes = [UNKNOWN, FREE, OCCUPIED]
    rule = {(UNKNOWN, FREE): FREE, (UNKNOWN, OCCUPIED): OCCUPIED, (FREE, FREE): FREE,
            (FREE, OCCUPIED): OCCUPIED, (OCCUPIED, FREE): OCCUPIED,
            (OCCUPIED, OCCUPIED): OCCUPIED}
    pairs = [(ours, theirs) for ours in codes for theirs in (FREE, OCCUPIED)]
    size = 4
    occupancy = OccupancyMap(size)
    book = MapSharing(1, occupancy)
    flat = np.arange(len(pairs)) * 5  # spread over columns: tops are checked too
    occupancy.update(flat, np.int8([ours for ours, _ in pairs]))
    book.note_sensed(0)
    top_before = occupancy.top.copy()
    delta = messages.MapDelta(1, flat, np.array([theirs == OCCUPIED for _, theirs in pairs]))
    changed = book.merge(delta, sender=0, round_=1)
    want = np.int8([rule[pair] for pair in pairs])
    np.testing.assert_array_equal(occupancy.codes[flat], want)
    assert changed == sum(rule[p] != p[0] for p in pairs) == 3
    assert book.conflicts == 2  # FREE against OCCUPIED, both ways
    # Tops: the highest OCCUPIED of either map per column.
    column, z = flat // size, flat % size
    for c in np.unique(column):
        held = z[(column == c) & (want == OCCUPIED)]
        assert occupancy.top.reshape(-1)[c] == max(top_before.reshape(-1)[c],
                                                   held.max() + 1 if held.size else 0)
    # A voxel freed nowhere is forwarded: the flip counts as learned from robot 0 now.
    flipped = flat[[pair == (FREE, OCCUPIED) for pair in pairs]]
    assert book.source[flipped].tolist() == [0] and book.learned[flipped].tolist() == [1]
    assert set(flipped) <= set(book.delta(2))


def test_occupied_from_an_authenticated_peer_reaches_the_team():
    """Robot 0 maps a voxel OCCUPIED that robots 1 and 2 hold FREE (a sensor that saw
    through a corner): after one map round both hold it OCCUPIED."""
    planners = team()
    voxel = np.int64([(G // 2 * G + G // 2) * G + 3])
    planners[0].map.mark_occupied(np.unravel_index(voxel[0], (G,) * 3))
    planners[0].sharing.note_sensed(0)
    outbox = [p.message() for p in planners]
    for i, p in enumerate(planners):
        for j, data in enumerate(outbox):
            if i != j:
                p.receive(data)
    maps = [p.map_message() for p in planners]
    for i, p in enumerate(planners):
        for j, data in enumerate(maps):
            if i != j:
                p.receive_map(data)
    assert [int(p.map.codes[voxel[0]]) for p in planners] == [OCCUPIED] * 3
    # Each robot met one disagreement per peer: the voxel FREE against OCCUPIED.
    assert [p.sharing.conflicts for p in planners] == [2, 2, 2]
    assert all(sum(p.rejected_messages.values()) == 0 for p in planners)


def test_a_restarted_sender_is_refused_until_its_seq_passes_the_last_taken():
    """The counter lives in the planner: a robot that restarts must resume above what it
    sent (`radio.sequence`), or its team refuses it as stale."""
    a, b, _ = team()
    for _ in range(3):
        b.receive(a.message())
    restarted = OnboardPlanner(SPEC, 0, budget=1.0, team_size=3, team_key=KEY)
    sense_free(restarted, position=(0.5, 0.3, 0.5))
    refused(b, b.receive, restarted.message(), "stale")
    restarted.radio.sequence = a.radio.sequence
    assert b.receive(restarted.message()).seq == 4
