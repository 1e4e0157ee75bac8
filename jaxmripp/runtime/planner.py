"""The onboard planner of one robot: own map, own GPs, radio, candidates, decision.

One planning round, on every robot, in this order (the JAX env's order, `jaxmripp.sim.env`):

    planner.sense(position, heading, voxels, values, n_seen)   # where I am, what I saw
    radio.broadcast(planner.message())                          # my waypoints + position
    for data in radio.received(): planner.receive(data)         # robots within range
    decision = planner.decide()                                 # -> decision.pose

`sense` charges the budget for the move just made, records the visited pose and the
number of windows seen from it, and writes the observed voxels into the map. `receive`
stores what a neighbour visited and where it is now. `decide` feeds the GPs (the rule of
`jaxmripp.spec.feeding`, in `feeding`), draws candidate poses (`candidates`) or takes ones
supplied by the caller, builds the policy's inputs (the rule of `jaxmripp.spec.layout`, in
`observation`), and picks the next pose with the exported policy or the greedy rule of
`jaxmripp.evaluation.baselines.greedy_planner`. Inputs are checked first (`validation`),
so a rejected call changes nothing.

Safety filter (`safety`): whatever picks the pose, it is chosen among candidates whose
straight flight crosses no voxel the robot knows to be OCCUPIED (exact voxel traversal,
start voxel included), that lie more than d_c from every robot heard this round, inside
the world and within the budget. If none is left the robot hovers: the decision is its
current pose, `hover` is True and `reason` says why.

Differences from the JAX env, on purpose: the radio is single hop (the paper's; a relay
export is refused by nothing but still runs single hop), a robot with no safe candidate
hovers and tries again next round instead of being retired, and the utility GP is always
the robot's own (a shared training-time GP does not exist on a robot).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from jaxmripp.runtime import candidates as cands
from jaxmripp.runtime import messages, observation, safety, validation
from jaxmripp.runtime.errors import MessageError, PlannerStateError
from jaxmripp.runtime.feeding import FeedSchedule
from jaxmripp.runtime.gp import GaussianProcess
from jaxmripp.runtime.mapping import OccupancyMap, segment_voxels
from jaxmripp.runtime.policy import NumpyPolicy
from jaxmripp.runtime.weights import RuntimeSpec
from jaxmripp.spec.grid import HEADING_ANGLES
from jaxmripp.spec.layout import FEATURES

F32 = np.float32
COL = {name: i for i, name in enumerate(FEATURES)}
MODES = validation.MODES


@dataclasses.dataclass(frozen=True)
class Decision:
    """The outcome of one `decide` call."""

    pose: np.ndarray  # (4,) float32 next waypoint (x, y, z, heading angle); current if hover
    position: np.ndarray  # (3,) float32
    heading: int  # heading index of `pose`
    index: int  # chosen candidate, -1 when hovering
    hover: bool
    reason: str  # "policy" / "greedy", or why the robot hovers
    mode: str
    scores: np.ndarray  # (L,) policy logits (infeasible floored) or greedy scores
    mask: np.ndarray  # (L,) bool candidates the rule could pick (offered and safe)
    safe: np.ndarray  # (L,) bool passed the safety filter
    features: np.ndarray  # (L, F) policy input, layout FEATURES
    robot_state: np.ndarray  # (S,) policy input, layout ROBOT_STATE
    candidates: cands.Candidates


class OnboardPlanner:
    """One robot's planner; see the module doc for the call order."""

    def __init__(
        self,
        spec: RuntimeSpec,
        robot_id: int,
        budget: float,
        team_size: int | None = None,
        policy: NumpyPolicy | None = None,
        mode: str | None = None,
        kappa: float = 1.0,
        lam: float = 0.0,
        max_steps: int | None = None,
        seed: int | None = None,
        segment_check: str = "exact",
    ):
        """spec: from the export header; budget: this robot's share of the team budget;
        team_size: robot ids are 0 .. team_size - 1 (default: the trained team size);
        mode: "policy" (needs `policy`) or "greedy" (score = utility mean + kappa * std -
        lam * communication mean); max_steps: the episode length the policy's step feature
        is normalised by (default: the export's); seed: candidate sampling (default: id);
        segment_check: how the safety filter tests a line of flight against the map --
        "exact" (every voxel the segment enters; the guarantee) or "sampled" (the JAX
        candidate rule's half-voxel samples, which can step over a voxel's corner; only for
        reproducing JAX decisions bit for bit)."""
        team_size = spec.team_size if team_size is None else int(team_size)
        mode = mode or ("policy" if policy is not None else "greedy")
        validation.settings(mode, policy is not None, robot_id, team_size, segment_check,
                            budget)
        self.spec = spec
        self.id = int(robot_id)
        self.team_size = team_size
        self.policy = policy
        self.mode = mode
        self.kappa, self.lam = float(kappa), float(lam)
        self.max_steps = spec.max_steps if max_steps is None else int(max_steps)
        self.rng = np.random.default_rng(self.id if seed is None else seed)
        self.segment_check = segment_check

        self.map = OccupancyMap(spec.size)
        self.utility_gp = GaussianProcess(spec.gp)
        self.comm_gp = GaussianProcess(spec.gp)
        self.feeding = FeedSchedule(self.id, team_size, spec.gp.catchup_rounds)
        self.memory = policy.initial_memory() if policy is not None else None
        self.budget_initial = F32(budget)
        self.budget_left = F32(budget)
        self.position: np.ndarray | None = None
        self.heading = 0
        self.step = 0
        # Own and peers' visited poses with their utilities: what the radio carries and
        # what `feeding` draws from.
        self.history_pose: list[np.ndarray] = []
        self.history_utility: list[np.float32] = []
        self.peer_pose: dict[int, list[np.ndarray]] = {j: [] for j in self._peer_ids()}
        self.peer_utility: dict[int, list[np.float32]] = {j: [] for j in self._peer_ids()}
        self.contacts: dict[int, np.ndarray] = {}  # positions heard this round, by sender
        self._command: tuple[np.ndarray, np.ndarray] | None = None  # (from, to) of last move

    @classmethod
    def load(cls, export: str | Path, robot_id: int, budget: float, **kwargs) -> "OnboardPlanner":
        """A planner driven by an exported policy (directory or policy.json)."""
        from jaxmripp.runtime.weights import load

        exported = load(export)
        return cls(exported.spec, robot_id, budget, policy=exported.policy, **kwargs)

    def _peer_ids(self):
        return [j for j in range(self.team_size) if j != self.id]

    # -----------------------------------------------------------------------------------
    # Inputs

    def sense(self, position, heading, voxels, values, n_seen: int, blocked: bool = False
              ) -> None:
        """Where the robot is now and what its camera saw from there.

        position (3,) in the unit cube and heading index 0..3 (+x, +y, -x, -y): the pose
        reached (short of the commanded one if `blocked`); voxels: observed voxels as flat
        C-order indices into (G, G, G) (G^3 marks "not observed" and is skipped) or as
        (K, 3) integer coordinates; values: their codes (0 free, 2 occupied); n_seen:
        windows seen from this pose. blocked: the last move was stopped by an obstacle;
        the voxel ahead on the commanded segment is then mapped occupied.
        """
        position = validation.position(position, "sense: position")
        heading = validation.heading(heading, "sense: heading")
        flat, codes = validation.observed(voxels, values, self.spec.size)
        n_seen = validation.n_seen(n_seen)

        first = self.position is None
        moved = first or self._command is not None  # a hover is not a visit
        if not first:
            self.step += 1
            if self._command is not None:
                self._charge(position, heading)
                if blocked:
                    self.map.mark_occupied(self._bumped_voxel(position))
        self.position, self.heading = position, heading
        self.map.update(flat, codes)
        if moved:
            self.history_pose.append(np.append(position, HEADING_ANGLES[heading]).astype(F32))
            self.history_utility.append(F32(n_seen) / F32(self.spec.utility_norm))
        self._command = None

    def message(self, start: int = 0) -> bytes:
        """This robot's radio broadcast: its history from `start` and its position."""
        self._require_sensed("message")
        start = min(max(int(start), 0), len(self.history_pose))
        poses = np.asarray(self.history_pose[start:], F32).reshape(-1, 4)
        return messages.encode(messages.Message(
            sender=self.id, position=self.position, heading=self.heading, start=start,
            poses=poses, utilities=np.asarray(self.history_utility[start:], F32)))

    def receive(self, data: bytes | str | messages.Message) -> messages.Message | None:
        """Takes one message heard this round; returns it (None for this robot's own echo)."""
        message = data if isinstance(data, messages.Message) else messages.decode(data)
        if message.sender == self.id:
            return None
        if message.sender >= self.team_size:
            raise MessageError(f"radio message from robot {message.sender}: ids of this team "
                               f"are 0 .. {self.team_size - 1}")
        self.contacts[message.sender] = np.asarray(message.position, F32)
        # Histories only grow: append the part past what we hold, if the message reaches it
        # (a message starting beyond our end would leave a gap, so it is not used).
        known = len(self.peer_utility[message.sender])
        if message.start <= known < message.end:
            fresh = known - message.start
            self.peer_pose[message.sender].extend(np.asarray(message.poses[fresh:], F32))
            self.peer_utility[message.sender].extend(np.asarray(message.utilities[fresh:], F32))
        return message

    # -----------------------------------------------------------------------------------
    # Decision

    def decide(self, candidates: Any = None, tie_break: np.ndarray | None = None,
               mode: str | None = None) -> Decision:
        """The next pose. candidates: optional externally supplied poses (an object with
        `position` (L, 3), `heading` (L,) and optionally `valid` (L,)) instead of sampling
        them; tie_break: (L,) added to greedy scores (jaxmripp's greedy adds 1e-5 x uniform
        noise; pass the same to reproduce its choices)."""
        self._require_sensed("decide")
        mode = validation.decide_mode(mode or self.mode, self.policy is not None)
        external = validation.external(candidates) if candidates is not None else None
        n = self.spec.n_candidates if external is None else len(external[0])
        tie_break = validation.tie_break(tie_break, n)

        self.feed_gps()
        stats: dict = {}
        c = self._sample(stats) if external is None else self._supplied(*external)
        features, robot_state = self.observe(c)
        safe, why = safety.check(c, self.position, self.budget_left, self.map,
                                 self._known_robots(), self.spec, self.segment_check)
        done = self.step >= self.max_steps
        mask = c.valid & safe & (not done)
        scores = self._scores(mode, features, mask, robot_state, tie_break)
        self.contacts = {}  # positions heard are good for this round only

        if not mask.any():
            reason = ("hover: step limit reached" if done else
                      safety.hover_reason(c, why, stats, self.budget_left, self.spec))
            return self._hover(mode, reason, scores, mask, safe, features, robot_state, c)
        index = int(np.argmax(np.where(mask, scores, -np.inf)))
        position, heading = c.position[index], int(c.heading[index])
        self._command = (self.position.copy(), position.copy())
        return Decision(
            pose=np.append(position, HEADING_ANGLES[heading]).astype(F32), position=position,
            heading=heading, index=index, hover=False, reason=mode, mode=mode, scores=scores,
            mask=mask, safe=safe, features=features, robot_state=robot_state, candidates=c)

    def feed_gps(self) -> None:
        """Feeds this round's pending poses into the GPs (`decide` does it first thing)."""
        self.feeding.feed(self.utility_gp, self.comm_gp, self.history_pose,
                          self.history_utility, self.peer_pose, self.peer_utility)

    def observe(self, c: cands.Candidates) -> tuple[np.ndarray, np.ndarray]:
        """The policy's inputs (features (L, F), robot_state (S,)) for candidates `c` from
        the robot's current state and GPs, without feeding or deciding anything."""
        self._require_sensed("observe")
        features = observation.candidate_features(
            c, self.position, self.budget_left, self.budget_initial, self.spec.shell[1],
            self.utility_gp, self.comm_gp)
        state = observation.robot_state(self.position, self.heading, self.budget_left,
                                        self.budget_initial, self.step, self.max_steps)
        return features, state

    # -----------------------------------------------------------------------------------
    # Internals

    def _require_sensed(self, what):
        if self.position is None:
            raise PlannerStateError(f"{what}: call sense() with the robot's first pose first")

    def _charge(self, position: np.ndarray, heading: int) -> None:
        """Budget for the move just made: distance as flown (to where the robot really is,
        short of the command if blocked) plus the turn cost on a heading change."""
        charge = np.linalg.norm(position - self.position).astype(F32) \
            + F32(self.spec.turn_cost) * F32(heading != self.heading)
        self.budget_left = F32(max(self.budget_left - charge, F32(0.0)))

    def _bumped_voxel(self, stop: np.ndarray) -> np.ndarray:
        """The voxel ahead of where the robot stopped on its commanded segment.

        jaxmripp.sim.env._fly: samples at the candidate spacing; a blocked robot stops at the
        last free sample (or its start) and the next sample's voxel is the obstacle.
        """
        start, end = self._command
        points, voxels = segment_voxels(start, end[None], self.spec.size, self.spec.shell[1])
        stops = np.concatenate([start[None], points[0, :-1]])
        first = int(np.argmin(np.sum(np.square(stops - stop), axis=-1)))
        return voxels[0, first]

    def _known_robots(self) -> np.ndarray:
        if not self.contacts:
            return np.zeros((0, 3), F32)
        return np.stack(list(self.contacts.values())).astype(F32)

    def _sample(self, stats: dict) -> cands.Candidates:
        """The robot's own candidates; the draw count is the JAX sampler's (draw 0 is the
        current position and needs no random numbers)."""
        uniforms = self.rng.random((self.spec.positions * self.spec.oversample - 1, 3), F32)
        return cands.sample(uniforms, self.position, self.heading, self.budget_left, self.map,
                            self._known_robots(), self.spec, stats)

    def _supplied(self, position, heading, valid) -> cands.Candidates:
        """Caller-supplied poses, costed by this robot; its current pose is never offered
        (a no-op step, excluded as the sampler excludes it)."""
        cost = cands.pose_cost(self.position, self.heading, position, heading,
                               self.spec.turn_cost)
        current = np.all(position == self.position, axis=-1) & (heading == self.heading)
        return cands.Candidates(position, heading, cost.astype(F32), valid & ~current)

    def _scores(self, mode, features, mask, robot_state, tie_break) -> np.ndarray:
        """Policy logits (the policy's memory advances) or the greedy UCB score."""
        if mode == "policy":
            self.memory, scores, _ = self.policy(self.memory, features, mask, robot_state)
            return scores
        f = features
        scores = f[:, COL["utility_mean"]] + self.kappa * f[:, COL["utility_std"]] \
            - self.lam * f[:, COL["comm_mean"]]
        return scores if tie_break is None else scores + tie_break

    def _hover(self, mode, reason, scores, mask, safe, features, robot_state, c) -> Decision:
        pose = np.append(self.position, HEADING_ANGLES[self.heading]).astype(F32)
        return Decision(pose=pose, position=self.position.copy(), heading=self.heading,
                        index=-1, hover=True, reason=reason, mode=mode, scores=scores,
                        mask=mask, safe=safe, features=features, robot_state=robot_state,
                        candidates=c)
