"""Onboard planner runtime: NumPy only, never imports jax or flax (it runs on drones).

    from jaxmripp.runtime import OnboardPlanner
    planner = OnboardPlanner.load("runs/default/export", robot_id=0, budget=10 / 3)
    planner.sense(position, heading, voxels, values, n_seen)   # every round (or sense_depth)
    radio.send(planner.message()); [planner.receive(m) for m in radio.inbox()]
    radio.send(planner.map_message()); [planner.receive_map(m) for m in radio.inbox()]
    planner.decide()                                            # the chosen pose
    radio.send(planner.intent_message()); [planner.receive_intent(m) for m in radio.inbox()]
    decision = planner.resolve()                                # decision.pose, .reason

The map round (the `map_message` line) runs with the export's `radio.share_maps` only. A
team that shares a secret key (`OnboardPlanner.load(..., team_key=key)`, every robot the
same `team_key()`) signs its messages and refuses others (`auth`). See
`jaxmripp.runtime.planner` for the round, `weights` for the export format and `messages`
for the radio protocol. The planner's parts: `validation` (inputs), `exchange` (its
broadcasts and receptions), `feeding` (GP feeding, rule in `jaxmripp.spec.feeding`),
`candidates` (sampling), `observation` (policy inputs, rule in `jaxmripp.spec.layout`),
`view` (the view gain, `jaxmripp.spec.view`), `belief` (the target belief,
`jaxmripp.spec.belief`), `depth` (depth images -> map updates, for
`sense_depth`), `sharing` (map deltas,
`jaxmripp.spec.sharing`), `safety` (the filter), `flight` (closest approach and the hold
rule, `jaxmripp.spec.flight`), `policy` (the network), `gp` and `mapping` (the map, its
building tops and the traversal rule of `jaxmripp.spec.grid`).
Every module here imports only NumPy, the standard library, `jaxmripp.spec` and other
runtime modules (tests/test_runtime_numpy_only.py checks it).
"""

from jaxmripp.runtime.auth import team_key
from jaxmripp.runtime.candidates import Candidates
from jaxmripp.runtime.depth import DepthCamera, GridFrame
from jaxmripp.runtime.errors import (CorruptWeightsError, InvalidPoseError, MessageError,
                                     PlannerStateError, ProtocolVersionError, RuntimeInputError,
                                     TeamKeyError, WeightsFormatError)
from jaxmripp.runtime.messages import (PROTOCOL_VERSION, MapDelta, MapMessage, Message, decode,
                                       decode_map, encode, encode_map)
from jaxmripp.runtime.planner import Decision, OnboardPlanner
from jaxmripp.runtime.policy import NumpyPolicy
from jaxmripp.runtime.weights import FORMAT_VERSION, ExportedPolicy, RuntimeSpec, load
from jaxmripp.spec.layout import FEATURES, ROBOT_STATE

__all__ = [
    "Candidates", "CorruptWeightsError", "Decision", "DepthCamera", "ExportedPolicy",
    "FEATURES", "FORMAT_VERSION", "GridFrame", "InvalidPoseError", "MapDelta", "MapMessage",
    "Message", "MessageError",
    "NumpyPolicy", "OnboardPlanner", "PROTOCOL_VERSION", "PlannerStateError",
    "ProtocolVersionError", "ROBOT_STATE", "RuntimeInputError", "RuntimeSpec",
    "TeamKeyError", "WeightsFormatError", "decode", "decode_map", "encode", "encode_map",
    "load", "team_key",
]
