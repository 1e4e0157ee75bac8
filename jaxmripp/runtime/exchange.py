"""The radio side of `OnboardPlanner`: the three broadcasts of a round and what the planner
takes from each (the order is in `jaxmripp.runtime.planner`'s docstring).

Kept apart from the planner so that each module reads as one part of the round: here what
goes out and comes in over the radio (`jaxmripp.spec.protocol`), there sensing and the
decision. `RadioExchange` is a base of `OnboardPlanner` and works on its state (`spec`,
`id`, `team_size`, the histories, `contacts`, `intents`, `sharing`, the round's flags).
"""

from __future__ import annotations

import numpy as np

from jaxmripp.runtime import messages
from jaxmripp.runtime.errors import MessageError, PlannerStateError

F32 = np.float32
ROUND = ("the round: sense, message / receive, map_message / receive_map, decide, "
         "intent_message / receive_intent, resolve")


class RadioExchange:
    """Broadcasts and receptions of `OnboardPlanner`."""

    def message(self, start: int = 0) -> bytes:
        """This robot's first broadcast of a round: its history from `start`, its position
        and its budget left (no intent)."""
        self._require_sensed("message")
        start = min(max(int(start), 0), len(self.history_pose))
        poses = np.asarray(self.history_pose[start:], F32).reshape(-1, 4)
        return messages.encode(messages.Message(
            sender=self.id, position=self.position, heading=self.heading, start=start,
            poses=poses, utilities=np.asarray(self.history_utility[start:], F32),
            budget_left=self.budget_left))

    def receive(self, data: bytes | str | messages.Message) -> messages.Message | None:
        """Takes one message heard this round; returns it (None for this robot's own echo)."""
        message = self._heard(data, messages.Message, messages.decode)
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
        data = messages.encode_map(self.sharing.message(self.contacts, self.step))
        self._map_sent = True
        self.last_map_message_bytes = len(data)
        return data

    def receive_map(self, data: bytes | str | messages.MapMessage
                    ) -> messages.MapMessage | None:
        """Takes one map message heard this round and merges the delta addressed to this
        robot, if any; returns the message (None for this robot's own echo)."""
        self._require_map_round("receive_map")
        if not self._map_sent:
            raise PlannerStateError("receive_map: call map_message() first this round (a "
                                    "robot sends its map as its own sensing left it)")
        message = self._heard(data, messages.MapMessage,
                              lambda raw: messages.decode_map(raw, self.spec.size))
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
        return messages.encode(messages.Message(
            sender=self.id, position=self.position, heading=self.heading, start=end,
            poses=np.zeros((0, 4), F32), utilities=np.zeros(0, F32),
            budget_left=self.budget_left,
            intent=None if decision.hover else decision.position))

    def receive_intent(self, data: bytes | str | messages.Message
                       ) -> messages.Message | None:
        """Takes one intent message (`intent_message`) heard after `decide`; returns it
        (None for this robot's own echo)."""
        self._require_decided("receive_intent")
        message = self._heard(data, messages.Message, messages.decode)
        if message is None:
            return None
        self.intents[message.sender] = (np.asarray(message.position, F32), message.intent,
                                        F32(message.budget_left))
        return message

    def _heard(self, data, kind, decode):
        """A decoded message (of class `kind`) from a teammate, or None for this robot's
        own echo."""
        message = data if isinstance(data, kind) else decode(data)
        if message.sender == self.id:
            return None
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
