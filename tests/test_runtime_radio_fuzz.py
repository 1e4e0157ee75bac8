"""Radio input is total: whatever bytes or text reach `receive`, `receive_map` or
`receive_intent`, the planner either takes a valid message or raises `MessageError` /
`ProtocolVersionError` (one line), counts the refusal once and changes nothing else.

Property-based (hypothesis, derandomised: the same cases every run): mutations of valid
messages of each kind (bytes flipped, inserted, deleted, truncated; JSON tokens such as
NaN, huge integers and deep nesting spliced in; one field replaced by any JSON value;
masks re-packed from truncated or altered zlib streams) and random bytes and text, to a
receiver with and without the team key, and to one with the target belief (whose map
deltas carry window bits). The named cases of the issue come first.
"""

from __future__ import annotations

import base64
import copy
import dataclasses
import json
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from jaxmripp.runtime import MessageError, OnboardPlanner, ProtocolVersionError, team_key
from jaxmripp.spec.protocol import MAX_BYTES
from test_runtime import sense_free
from test_runtime_auth import SPEC, fingerprint

KEY = team_key(11)
REFUSALS = (MessageError, ProtocolVersionError)
FAST = settings(max_examples=200, derandomize=True, database=None, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
MANY = settings(FAST, max_examples=5000)


def prepared(key, spec=SPEC):
    """Robot 0 with a history, the messages it sends in one round, and robot 1 ready for
    each reception: `mapping` in the map round, `intents` after its decision. With the
    target belief robot 0 has also mapped a wall with windows, which its delta carries."""
    a, b = (OnboardPlanner(spec, i, budget=1.0, team_size=3, team_key=key) for i in range(2))
    for k, z in enumerate((0.3, 0.4, 0.5)):  # three visited poses to carry
        sense_free(a, position=(0.5, 0.5, z), n_seen=k)
        a._command = (a.position, a.position)
    if spec.belief_features:
        wall = np.arange(5) + (2 * spec.size + 3) * spec.size  # column (2, 3), z 0 .. 4
        a.sense(a.position, 1, wall, np.full(5, 2, np.int8), 0, windows=wall[[1, 3]])
    sense_free(b, position=(0.5, 0.8, 0.5))
    flat = np.arange(0, SPEC.size ** 3, 3)
    b.sense(b.position, 1, flat, np.where(flat % 7 == 0, 2, 0).astype(np.int8), 0)
    b.receive(a.message())  # earlier contact: later messages carry seq 2 on
    a.receive(b.message())
    sent = {"receive": a.message(), "receive_map": a.map_message()}
    a.decide()
    sent["receive_intent"] = a.intent_message()
    mapping = copy.deepcopy(b)
    mapping.map_message()
    intents = copy.deepcopy(mapping)
    intents.decide()
    return sent, {"receive": mapping, "receive_map": mapping, "receive_intent": intents}


SIDES = {"keyless": prepared(None), "keyed": prepared(KEY),
         "belief": prepared(None, dataclasses.replace(SPEC, belief_features=True,
                                                      belief_prior=0.04))}
KINDS = ("receive", "receive_map", "receive_intent")


class Receiver:
    """A working copy of a prepared receiver and its fingerprint; a fresh copy replaces
    it after every message it takes (so each case meets the prepared state)."""

    def __init__(self, side, call):
        self.pristine = SIDES[side][1][call]
        self.renew()

    def renew(self):
        self.planner = copy.deepcopy(self.pristine)
        self.fingerprint = fingerprint(self.planner)


RECEIVERS: dict = {}


def total(side: str, call: str, data) -> bool:
    """The property: True when the message was taken, False when refused (checked)."""
    receiver = RECEIVERS.get((side, call)) or RECEIVERS.setdefault((side, call),
                                                                   Receiver(side, call))
    planner = receiver.planner
    counts = sum(planner.rejected_messages.values())
    try:
        getattr(planner, call)(data)
    except REFUSALS as error:
        text = str(error)
        assert "\n" not in text and 0 < len(text) < 400, text
        assert fingerprint(planner) == receiver.fingerprint, f"{call} refused and changed " \
                                                             "the planner"
        assert sum(planner.rejected_messages.values()) == counts + 1
        return False
    receiver.renew()
    return True


# ---------------------------------------------------------------------------------------
# The named cases


def record_of(side, call):
    return json.loads(SIDES[side][0][call])


def with_field(call, name, text):
    """The keyless message of `call` with field `name` written as raw JSON `text`."""
    data = SIDES["keyless"][0][call].decode()
    record = record_of("keyless", call)
    marker = '"@@@"'
    return json.dumps(dict(record, **{name: "@@@"}), separators=(",", ":")).replace(
        marker, text)


def deep(levels):
    return "[" * levels + "]" * levels


NAMED = {
    "5000-digit integer (a 5 KB status message)": ("receive", with_field(
        "receive", "budget_left", "9" * 5000)),
    "5000-digit integer as the sender": ("receive", with_field("receive", "sender",
                                                               "1" * 5000)),
    "20-digit heading": ("receive", with_field("receive", "heading", "1" + "0" * 19)),
    "NaN": ("receive", with_field("receive", "budget_left", "NaN")),
    "Infinity in a pose": ("receive", with_field("receive", "position", "[0.5,Infinity,0.5]")),
    "-Infinity": ("receive_intent", with_field("receive_intent", "intent",
                                               "[0.5,0.5,-Infinity]")),
    "1e999": ("receive", with_field("receive", "utilities", "[1e999,0,0]")),
    "beyond float32": ("receive", with_field("receive", "utilities", "[1e39,0,0]")),
    "nested 100000 deep": ("receive", deep(100_000)),
    "nested in a field": ("receive_map", with_field("receive_map", "deltas", deep(50_000))),
    "nested 900 deep in a field": ("receive", with_field("receive", "heading", deep(900))),
    "str over the size cap": ("receive", " " * (MAX_BYTES + 1)),
    "str over the size cap in UTF-8 only": ("receive", "\u00e9" * (MAX_BYTES // 2 + 1)),
    "lone surrogate": ("receive", with_field("receive", "type", '"\ud800"')),
    "escaped lone surrogate": ("receive", with_field("receive", "type", '"\\ud800"')),
    "not UTF-8": ("receive", b"\xff\xfe{}"),
    "a list": ("receive", []), "a dict": ("receive", {}), "None": ("receive", None),
    "an int": ("receive_map", 5),
    "sender out of the team": ("receive", with_field("receive", "sender", "3")),
    "negative sender": ("receive_intent", with_field("receive_intent", "sender", "-1")),
    "sender true": ("receive", with_field("receive", "sender", "true")),
    "seq beyond 2^63": ("receive", with_field("receive", "seq", str(2 ** 63))),
    "heading 4": ("receive", with_field("receive", "heading", "4")),
    "position outside": ("receive", with_field("receive", "position", "[0.5,1.5,0.5]")),
    "negative budget": ("receive", with_field("receive", "budget_left", "-0.5")),
    "size mismatch": ("receive_map", with_field("receive_map", "size", str(SPEC.size + 1))),
    "protocol 3": ("receive", with_field("receive", "protocol", "3")),
}


def mask_case(name):
    """The keyless map message with its first delta's voxel mask replaced."""
    record = record_of("keyless", "receive_map")
    entry = record["deltas"][0]
    raw = zlib.decompress(base64.b64decode(entry["voxels"]))
    stream = zlib.compress(raw)
    packed = {
        "truncated zlib": stream[:len(stream) // 2],
        "zlib without its end": stream[:-4],
        "a voxel past the grid": zlib.compress(raw + b"\x80"),  # bit G^3 set
        "a mask one byte shorter": zlib.compress(raw[:-1]),
    }[name]
    entry["voxels"] = base64.b64encode(packed).decode()
    return json.dumps(record)


MASKS = ("truncated zlib", "zlib without its end", "a voxel past the grid",
         "a mask one byte shorter")


@pytest.mark.parametrize("name", list(NAMED) + list(MASKS))
def test_named_malformed_messages_are_refused_and_change_nothing(name):
    call, data = NAMED[name] if name in NAMED else ("receive_map", mask_case(name))
    for side in SIDES:
        assert not total(side, call, data), f"{side}: {name} was taken"


def test_valid_messages_are_taken_on_both_sides():
    """The property's other branch: the unmutated messages pass (so mutants that fail
    are refused for what was changed)."""
    for side in SIDES:
        for call in KINDS:
            assert total(side, call, SIDES[side][0][call]), (side, call)


# ---------------------------------------------------------------------------------------
# Mutations


TOKENS = [b"NaN", b"Infinity", b"-Infinity", b"1e999", b"-1e400", b"9" * 5000,
          b"-" + b"1" * 25, b"1e39", b"[" * 3000, b"{\"a\":" * 3000, b"null", b"true",
          b"\"\\ud800\"", b"\xff", b"\xed\xa0\x80", b"\"", b",", b"}", b"]", b"0",
          b"-0.0", b"1e-320", b"\"tag\":\"" + b"A" * 44 + b"\","]
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-2 ** 70, 2 ** 70)
    | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner,
                                                                 max_size=5),
    max_leaves=12)


@st.composite
def byte_mutants(draw, base: bytes) -> bytes:
    data = bytearray(base)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(("flip", "insert", "delete", "truncate", "token")))
        at = draw(st.integers(0, len(data)))
        if op == "flip" and at < len(data):
            data[at] ^= draw(st.integers(1, 255))
        elif op == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del data[at:at + draw(st.integers(1, 16))]
        elif op == "truncate":
            del data[at:]
        elif op == "token":
            end = at + draw(st.integers(0, 12))
            data[at:end] = draw(st.sampled_from(TOKENS))
    return bytes(data)


@st.composite
def field_mutants(draw, base: bytes) -> str:
    """One field (or, in a map message, one delta's field) replaced by any JSON value."""
    record = json.loads(base)
    target = record
    if "deltas" in record and record["deltas"] and draw(st.booleans()):
        target = record["deltas"][0]
    name = draw(st.sampled_from(sorted(target) + ["extra"]))
    if draw(st.booleans()):
        target[name] = draw(JSON_VALUES)
    else:
        target.pop(name, None)
    return json.dumps(record, allow_nan=True)


@st.composite
def mask_mutants(draw, base: bytes) -> str:
    """A map message whose masks come from altered or truncated zlib streams."""
    record = json.loads(base)
    entry = record["deltas"][0]
    field = draw(st.sampled_from(tuple(k for k in ("voxels", "occupied", "windows")
                                       if k in entry)))
    raw = zlib.decompress(base64.b64decode(entry[field]))
    if draw(st.booleans()) and raw:
        at = draw(st.integers(0, len(raw) - 1))
        raw = raw[:at] + bytes([raw[at] ^ draw(st.integers(1, 255))]) + raw[at + 1:]
    stream = zlib.compress(raw + draw(st.binary(max_size=3)))
    cut = draw(st.integers(0, len(stream)))
    entry[field] = base64.b64encode(stream[:cut] if draw(st.booleans()) else stream).decode()
    return json.dumps(record)


def mutants(side, call):
    base = SIDES[side][0][call]
    strategies = [byte_mutants(base), field_mutants(base)]
    if call == "receive_map":
        strategies.append(mask_mutants(base))
    return st.one_of(strategies)


def run_mutants(side, call, budget):
    """The property over mutants; returns how many were (taken, refused)."""
    original = SIDES[side][0][call]
    outcomes = []

    @budget
    @given(data=mutants(side, call))
    def property_(data):
        taken = total(side, call, data)
        if side == "keyed" and taken:  # the tag covers every byte
            assert (data.encode() if isinstance(data, str) else data) == original
        outcomes.append(taken)

    property_()
    return sum(outcomes), len(outcomes) - sum(outcomes)


@pytest.mark.parametrize("side", list(SIDES))
@pytest.mark.parametrize("call", KINDS)
def test_mutated_messages_are_taken_or_refused_cleanly(side, call):
    taken, refused = run_mutants(side, call, FAST)
    # Both branches are met: mutants that keep a valid message (a digit of a float, a
    # field removed that has a default) and ones refused.
    assert refused > taken > 0 if side == "keyless" else refused > 0


@settings(FAST, max_examples=400)
@given(call=st.sampled_from(KINDS), data=st.binary(max_size=300) | st.text(max_size=300),
       side=st.sampled_from(list(SIDES)))
def test_random_bytes_and_text_are_refused(call, data, side):
    assert not total(side, call, data)


@pytest.mark.slow
@pytest.mark.parametrize("side", list(SIDES))
@pytest.mark.parametrize("call", KINDS)
def test_many_more_mutated_messages(side, call):
    taken, refused = run_mutants(side, call, MANY)
    assert refused > taken
