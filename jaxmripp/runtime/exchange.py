"""The radio side of `OnboardPlanner`: the three broadcasts of a round and what the planner
takes from each (the order is in `jaxmripp.runtime.planner`'s docstring).

Kept apart from the planner so that each module reads as one part of the round: here what
goes out and comes in over the radio (`jaxmripp.spec.protocol`), there sensing and the
decision. `RadioExchange` is a base of `OnboardPlanner` and works on its state (`spec`,
`id`, `team_size`, the histories, `sharing`, the round's flags) and keeps the radio's own
(`_init_radio`). With a team key (`jaxmripp.runtime.auth`) every broadcast is signed and
every reception checked; whatever a reception refuses is counted in `rejected_messages`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxmripp.runtime import auth, messages
from jaxmripp.runtime.errors import MessageError, PlannerStateError, ProtocolVersionError
from jaxmripp.spec.protocol import MAP_MESSAGE_TYPE, MESSAGE_TYPE

F32 = np.float32
ROUND = ("the round: sense, message / receive, map_message / receive_map, decide, "
         "intent_message / receive_intent, resolve")


class RadioExchange:
    """Broadcasts and receptions of `OnboardPlanner`."""

    def _init_radio(self, team_key: bytes | None) -> None:
        """The radio's state of a new planner (after `id`)."""
        self.radio = auth.RadioAuth(team_key, self.id)
        self.contacts: dict[int, np.ndarray] = {}  # positions heard this round, by sender
        self.intents: dict[int, tuple] = {}  # sender -> (position, target or None)
        self.last_map_message_bytes: int | None = None

    @property
    def rejected_messages(self) -> dict[str, int]:
        """Messages `receive`, `receive_map` and `receive_intent` refused, by reason
        (`jaxmripp.runtime.auth.REASONS`: malformed, version, and with a team key
        unsigned, forged, stale)."""
        return dict(self.radio.rejected)

    def message(self, start: int = 0) -> bytes:
        """This robot's first broadcast of a round: its history from `start`, its position
        and its budget left (no intent)."""
        self._require_sensed("message")
        start = min(max(int(start), 0), len(self.history_pose))
        poses = np.asarray(self.history_pose[start:], F32).reshape(-1, 4)
        seq = self.radio.next_sequence()
        return self.radio.seal(messages.encode(messages.Message(
            sender=self.id, position=self.position, heading=self.heading, start=start,
            poses=poses, utilities=np.asarray(self.history_utility[start:], F32),
            budget_left=self.budget_left, seq=seq)), seq)

    def receive(self, data: bytes | str | messages.Message) -> messages.Message | None:
        """Takes one message heard this round; returns it (None for this robot's own echo)."""
        message = self._heard(data, messages.Message, messages.read_message)
        if message is None:
            return None
        self.contacts[message.sender] = np.asarray(message.position, F32)
        # Histories only grow: append the part past what we hold, if the message reaches it
        # (a message starting beyond our end would leave a gap, so it is not used).
        known = len(self.peer_utility[message.sender])
        if message.start <= known < message.end:
            fresh = known - message.start
            self.peer_pose[message.sender].extend(np.asarray(message.poses[fresh:], F32))
            self.peer_utility[message.sender].extend(np.asarray(message.utilities[fresh:], F32))
        return message

    def map_message(self) -> bytes:
        """The map broadcast (with `spec.share_maps`), once per round after `receive` and
        before `decide`: for every robot heard this round, the voxels of this robot's map
        it may lack (`jaxmripp.runtime.sharing`). Its size in bytes is kept in
        `last_map_message_bytes`."""
        self._require_map_round("map_message")
        if self._map_sent:
            raise PlannerStateError(f"map_message: already sent this round ({ROUND})")
        seq = self.radio.next_sequence()
        deltas = self.sharing.message(self.contacts, self.step)
        data = self.radio.seal(messages.encode_map(dataclasses.replace(deltas, seq=seq)), seq)
        self._map_sent = True
        self.last_map_message_bytes = len(data)
        return data

    def receive_map(self, data: bytes | str | messages.MapMessage
                    ) -> messages.MapMessage | None:
        """Takes one map message heard this round and merges the delta addressed to this
        robot, if any (with the target belief its window bits too); returns the message
        (None for this robot's own echo)."""
        self._require_map_round("receive_map")
        if not self._map_sent:
            raise PlannerStateError("receive_map: call map_message() first this round (a "
                                    "robot sends its map as its own sensing left it)")
        message = self._heard(data, messages.MapMessage,
                              lambda envelope: messages.read_map(
                                  envelope, self.spec.size, self.spec.belief_features))
        if message is None:
            return None
        if message.size != self.spec.size:
            raise MessageError(f"map message from robot {message.sender}: its map has size "
                               f"{message.size}, this robot's {self.spec.size}")
        delta = message.delta_for(self.id)
        if delta is not None:
            self.sharing.merge(delta, message.sender, self.step)
        return message

    def intent_message(self) -> bytes:
        """This robot's second broadcast of a round, after `decide`: the target of the
        flight it chose (null when it hovers), its position and budget left; no poses."""
        decision = self._require_decided("intent_message")
        end = len(self.history_pose)
        seq = self.radio.next_sequence()
        return self.radio.seal(messages.encode(messages.Message(
            sender=self.id, position=self.position, heading=self.heading, start=end,
            poses=np.zeros((0, 4), F32), utilities=np.zeros(0, F32),
            budget_left=self.budget_left, intent=None if decision.hover else decision.position,
            seq=seq)), seq)

    def receive_intent(self, data: bytes | str | messages.Message
                       ) -> messages.Message | None:
        """Takes one intent message (`intent_message`) heard after `decide`; returns it
        (None for this robot's own echo)."""
        self._require_decided("receive_intent")
        message = self._heard(data, messages.Message, messages.read_message)
        if message is None:
            return None
        self.intents[message.sender] = (np.asarray(message.position, F32), message.intent)
        return message

    def _heard(self, data, kind, read):
        """A checked message (of class `kind`, its fields read from a parsed envelope by
        `read`) from a teammate, or None for this robot's own echo. Checks everything
        before anything changes; a refusal is counted by its reason and raised."""
        try:
            if isinstance(data, kind):
                self.radio.object_allowed(kind.__name__)
                return None if data.sender == self.id else self._teammate(data)
            envelope = messages.parse(data, MAP_MESSAGE_TYPE if kind is messages.MapMessage
                                      else MESSAGE_TYPE)
            if envelope.sender == self.id:
                return None
            self._teammate(envelope)
            self.radio.check(envelope)
            message = read(envelope)
        except ProtocolVersionError:
            self.radio.rejected["version"] += 1
            raise
        except MessageError as error:
            self.radio.rejected[error.reason] += 1
            raise
        self.radio.accept(envelope)
        return message

    def _known_robots(self) -> np.ndarray:
        """(K, 3) float32 positions of the robots heard this round."""
        if not self.contacts:
            return np.zeros((0, 3), F32)
        return np.stack(list(self.contacts.values())).astype(F32)

    def _teammate(self, message):
        """`message` (anything with a `sender`) if its sender is an id of this team."""
        if message.sender >= self.team_size:
            raise MessageError(f"radio message from robot {message.sender}: ids of this team "
                               f"are 0 .. {self.team_size - 1}")
        return message

    def _require_map_round(self, what) -> None:
        self._require_sensed(what)
        if not self.spec.share_maps:
            raise PlannerStateError(f"{what}: this export does not share maps "
                                    "(config radio.share_maps is false)")
        if self._decided:
            raise PlannerStateError(f"{what}: maps are exchanged before decide() ({ROUND})")
