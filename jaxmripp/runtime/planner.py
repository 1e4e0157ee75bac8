"""The onboard planner of one robot: own map, own GPs, radio, candidates, decision.

One planning round, on every robot, in this order (the JAX env's order, jaxmripp/env.py):

    planner.sense(position, heading, voxels, values, n_seen)   # where I am, what I saw
    radio.broadcast(planner.message())                          # my waypoints + position
    for data in radio.received(): planner.receive(data)         # robots within range
    decision = planner.decide()                                 # -> decision.pose

`sense` charges the budget for the move just made, records the visited pose and the
number of windows seen from it, and writes the observed voxels into the map. `receive`
stores what a neighbour visited and where it is now. `decide` feeds the GPs (own newest
pose first, then N - 1 + `gp.catchup_rounds` peer rounds, each taking the oldest pending
pose of the peer with the largest backlog), draws candidate poses (or takes ones
supplied by the caller), builds the policy's inputs exactly as `jaxmripp.sim.env.observe`
does, and picks the next pose with the exported policy or the greedy rule of
`jaxmripp.evaluation.baselines.greedy_planner`.

Safety filter: whatever picks the pose, it is chosen among candidates whose straight flight
crosses no voxel the robot knows to be OCCUPIED (exact voxel traversal, start voxel
included), that lie more than d_c from every robot heard this round, inside the world and
within the budget. If none is left the robot hovers: the decision is its current pose,
`hover` is True and `reason` says why.

Differences from the JAX env, on purpose: the radio is single hop (the paper's; a relay
export is refused by nothing but still runs single hop), a robot with no safe candidate
hovers and tries again next round instead of being retired, and the utility GP is always
the robot's own (a shared training-time GP does not exist on a robot).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from jaxmripp.runtime import candidates as cands
from jaxmripp.runtime import messages
from jaxmripp.runtime.errors import InvalidPoseError, MessageError, PlannerStateError
from jaxmripp.runtime.gp import GaussianProcess
from jaxmripp.runtime.mapping import (HEADING_ANGLES, N_HEADINGS, OCCUPIED, OccupancyMap,
                                      segment_voxels)
from jaxmripp.runtime.policy import NumpyPolicy
from jaxmripp.runtime.weights import FEATURES, RuntimeSpec

F32 = np.float32
COL = {name: i for i, name in enumerate(FEATURES)}
MODES = ("policy", "greedy")


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
        if mode not in MODES:
            raise ValueError(f"mode: got {mode!r}; allowed: {', '.join(MODES)}")
        if mode == "policy" and policy is None:
            raise ValueError("mode 'policy' needs a policy (OnboardPlanner.load an export)")
        if not 0 <= int(robot_id) < team_size:
            raise ValueError(f"robot_id: got {robot_id}; allowed: 0 .. {team_size - 1}")
        if segment_check not in ("exact", "sampled"):
            raise ValueError(f"segment_check: got {segment_check!r}; allowed: exact, sampled")
        if not (math.isfinite(budget) and budget > 0):
            raise ValueError(f"budget: got {budget}; allowed: a positive number")
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
        self.memory = policy.initial_memory() if policy is not None else None
        self.budget_initial = F32(budget)
        self.budget_left = F32(budget)
        self.position: np.ndarray | None = None
        self.heading = 0
        self.step = 0
        self.history_pose: list[np.ndarray] = []
        self.history_utility: list[np.float32] = []
        self.own_fed = 0
        self.peer_pose: dict[int, list[np.ndarray]] = {j: [] for j in self._peer_ids()}
        self.peer_utility: dict[int, list[np.float32]] = {j: [] for j in self._peer_ids()}
        self.peer_fed: dict[int, int] = {j: 0 for j in self._peer_ids()}
        self.contacts: dict[int, np.ndarray] = {}
        self._command: tuple[np.ndarray, np.ndarray] | None = None  # (from, to) of last move
        # jaxmripp.sim.env._feed_gps: peers by offset 1..n-1 (its tie order), a fixed round count.
        n = team_size
        self._peers_by_offset = [(self.id + offset) % n for offset in range(1, n)]
        self._peer_rounds = n - 1 + spec.gp.catchup_rounds if n > 1 else 0

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
        position = _position(position, "sense: position")
        heading = _heading(heading, "sense: heading")
        flat, codes = self._observed(voxels, values)
        if isinstance(n_seen, (bool, np.bool_)) or not isinstance(n_seen, (int, np.integer)) \
                or n_seen < 0:
            raise InvalidPoseError(f"sense: n_seen must be a non-negative integer, got {n_seen!r}")

        first = self.position is None
        moved = first or self._command is not None
        if not first:
            self.step += 1
            if self._command is not None:
                charge = np.linalg.norm(position - self.position).astype(F32) \
                    + F32(self.spec.turn_cost) * F32(heading != self.heading)
                self.budget_left = F32(max(self.budget_left - charge, F32(0.0)))
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
        mode = mode or self.mode
        if mode not in MODES or (mode == "policy" and self.policy is None):
            raise ValueError(f"mode: got {mode!r}; allowed: greedy" +
                             (", policy" if self.policy is not None else ""))
        external = _external(candidates) if candidates is not None else None
        n = self.spec.n_candidates if external is None else len(external[0])
        if tie_break is not None:
            tie_break = np.asarray(tie_break, F32)
            if tie_break.shape != (n,) or not np.all(np.isfinite(tie_break)):
                raise InvalidPoseError(f"decide: tie_break must be ({n},) finite numbers")

        self._feed_gps()
        stats: dict = {}
        if external is None:
            uniforms = self.rng.random((self.spec.positions * self.spec.oversample - 1, 3), F32)
            c = cands.sample(uniforms, self.position, self.heading, self.budget_left, self.map,
                             self._known_robots(), self.spec, stats)
        else:
            position, heading, valid = external
            cost = cands.pose_cost(self.position, self.heading, position, heading,
                                   self.spec.turn_cost)
            current = np.all(position == self.position, axis=-1) & (heading == self.heading)
            c = cands.Candidates(position, heading, cost.astype(F32), valid & ~current)

        features, robot_state = self._features(c)
        safe, why = self._safety(c)
        done = self.step >= self.max_steps
        mask = c.valid & safe & (not done)

        if mode == "policy":
            self.memory, scores, _ = self.policy(self.memory, features, mask, robot_state)
        else:
            f = features
            scores = f[:, COL["utility_mean"]] + self.kappa * f[:, COL["utility_std"]] \
                - self.lam * f[:, COL["comm_mean"]]
            if tie_break is not None:
                scores = scores + tie_break
        self.contacts = {}

        if not mask.any():
            reason = ("hover: step limit reached" if done else
                      self._hover_reason(c, safe, why, stats))
            return self._hover(mode, reason, scores, mask, safe, features, robot_state, c)
        index = int(np.argmax(np.where(mask, scores, -np.inf)))
        position, heading = c.position[index], int(c.heading[index])
        self._command = (self.position.copy(), position.copy())
        return Decision(
            pose=np.append(position, HEADING_ANGLES[heading]).astype(F32), position=position,
            heading=heading, index=index, hover=False, reason=mode, mode=mode, scores=scores,
            mask=mask, safe=safe, features=features, robot_state=robot_state, candidates=c)

    # -----------------------------------------------------------------------------------
    # Internals

    def _require_sensed(self, what):
        if self.position is None:
            raise PlannerStateError(f"{what}: call sense() with the robot's first pose first")

    def _observed(self, voxels, values):
        g = self.spec.size
        voxels, values = np.asarray(voxels), np.asarray(values)
        if voxels.ndim == 2 and voxels.shape[1] == 3:
            if not np.issubdtype(voxels.dtype, np.integer) or np.any((voxels < 0) | (voxels >= g)):
                raise InvalidPoseError(f"sense: voxel coordinates must be integers in 0..{g - 1}")
            voxels = (voxels[:, 0] * g + voxels[:, 1]) * g + voxels[:, 2]
        if voxels.ndim != 1 or values.shape != voxels.shape:
            raise InvalidPoseError(f"sense: voxels {voxels.shape} and values {values.shape} must "
                                   "be matching 1-D arrays (or (K, 3) coordinates)")
        if voxels.size and (not np.issubdtype(voxels.dtype, np.integer)
                            or voxels.min() < 0 or voxels.max() > g ** 3):
            raise InvalidPoseError(f"sense: flat voxel indices must be integers in 0..{g ** 3}")
        seen = voxels < g ** 3
        codes = values[seen]
        if codes.size and (not np.issubdtype(codes.dtype, np.integer)
                           or codes.min() < 0 or codes.max() > OCCUPIED):
            raise InvalidPoseError("sense: voxel values must be codes 0 (free), 1, 2 (occupied)")
        return voxels[seen].astype(np.int64), codes.astype(np.int8)

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

    def _feed_gps(self) -> None:
        """jaxmripp.sim.env._feed_gps for this robot: own pose, then the largest backlogs."""
        if self.own_fed < len(self.history_pose):
            self.utility_gp.add(self.history_pose[self.own_fed], self.history_utility[self.own_fed])
            self.own_fed += 1
        for _ in range(self._peer_rounds):
            j = max(self._peers_by_offset,  # max keeps the first maximum, as argmax does
                    key=lambda peer: len(self.peer_utility[peer]) - self.peer_fed[peer])
            index = self.peer_fed[j]
            if index < len(self.peer_utility[j]):
                pose = self.peer_pose[j][index]
                self.utility_gp.add(pose, self.peer_utility[j][index])
                self.comm_gp.add(pose, F32(1.0))
                self.peer_fed[j] = index + 1

    def _known_robots(self) -> np.ndarray:
        if not self.contacts:
            return np.zeros((0, 3), F32)
        return np.stack(list(self.contacts.values())).astype(F32)

    def _features(self, c: cands.Candidates) -> tuple[np.ndarray, np.ndarray]:
        """Per-candidate features and robot state, as jaxmripp.sim.env.observe builds them."""
        poses = np.concatenate([c.position, HEADING_ANGLES[c.heading][:, None]], axis=1)
        u_mean, u_var = self.utility_gp.predict(poses)
        c_mean, c_var = self.comm_gp.predict(poses)
        onehot = np.eye(N_HEADINGS, dtype=F32)[c.heading]
        budget = max(self.budget_initial, F32(1e-6))
        features = np.concatenate([
            (c.position - self.position) / F32(self.spec.shell[1]),
            c.position,
            onehot,
            u_mean[:, None], np.sqrt(u_var)[:, None],
            c_mean[:, None], np.sqrt(c_var)[:, None],
            c.cost[:, None],
            ((self.budget_left - c.cost) / budget)[:, None],
        ], axis=1).astype(F32)
        robot_state = np.concatenate([
            self.position,
            np.eye(N_HEADINGS, dtype=F32)[self.heading],
            [self.budget_left / budget],
            [F32(self.step) / F32(self.max_steps)],
        ]).astype(F32)
        return features, robot_state

    def _safety(self, c: cands.Candidates) -> tuple[np.ndarray, dict]:
        """(L,) bool safe, and per-rule rejections (L,) bool each."""
        finite = np.all(np.isfinite(c.position), axis=-1)
        position = np.where(finite[:, None], c.position, self.position)
        outside = ~np.all((position >= 0.0) & (position <= 1.0), axis=-1) | ~finite
        # Candidates share positions four by four: traverse each distinct segment once.
        unique, inverse = np.unique(position, axis=0, return_inverse=True)
        if self.segment_check == "exact":
            clear = self.map.exact_clear(self.position, unique)
        else:
            clear = self.map.sampled_clear(self.position, unique, self.spec.shell[1])
        blocked = ~clear[inverse.reshape(-1)]
        crowded = ~cands.clear_of_robots(position, self._known_robots(),
                                         self.spec.collision_distance)
        over_budget = ~(c.cost <= self.budget_left)
        why = {"outside": outside, "blocked": blocked, "crowded": crowded,
               "over_budget": over_budget}
        return ~(outside | blocked | crowded | over_budget), why

    def _hover_reason(self, c, safe, why, stats) -> str:
        budget = float(self.budget_left)
        cheapest = min(self.spec.turn_cost, self.spec.shell[0])
        if budget < cheapest:
            return (f"hover: budget exhausted ({budget:.4g} left, the cheapest move costs "
                    f"{cheapest:g})")
        offered = c.valid
        if not offered.any():
            if stats:
                counts = ", ".join(f"{stats[k]} {text}" for k, text in (
                    ("outside", "outside the world"), ("blocked", "behind known obstacles"),
                    ("crowded", "within d_c of a robot heard"), ("over_budget", "over budget"))
                    if stats[k])
                return f"hover: no candidate left of {stats['draws']} draws ({counts})"
            return "hover: none of the supplied candidates is offered as valid"
        counts = ", ".join(f"{int((why[k] & offered).sum())} {text}" for k, text in (
            ("blocked", "cross a voxel known occupied"),
            ("crowded", f"within d_c = {self.spec.collision_distance:g} of a robot heard"),
            ("over_budget", f"over the budget left ({budget:.4g})"),
            ("outside", "outside the world")) if (why[k] & offered).any())
        return f"hover: the safety filter rejected all {int(offered.sum())} candidates ({counts})"

    def _hover(self, mode, reason, scores, mask, safe, features, robot_state, c) -> Decision:
        pose = np.append(self.position, HEADING_ANGLES[self.heading]).astype(F32)
        return Decision(pose=pose, position=self.position.copy(), heading=self.heading,
                        index=-1, hover=True, reason=reason, mode=mode, scores=scores,
                        mask=mask, safe=safe, features=features, robot_state=robot_state,
                        candidates=c)


# ---------------------------------------------------------------------------------------
# Validation helpers (raise before anything changes)


def _position(value, name) -> np.ndarray:
    try:
        position = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidPoseError(f"{name} must be 3 numbers, got {value!r}") from None
    if position.shape != (3,):
        raise InvalidPoseError(f"{name} must be 3 numbers, got shape {position.shape}")
    if not np.all(np.isfinite(position)):
        raise InvalidPoseError(f"{name} is not finite: {position.tolist()}")
    if np.any((position < 0.0) | (position > 1.0)):
        raise InvalidPoseError(f"{name} {position.tolist()} lies outside the unit cube")
    return position.astype(F32)


def _heading(value, name) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or not 0 <= int(value) < N_HEADINGS:
        raise InvalidPoseError(f"{name} must be a heading index 0..3, got {value!r}")
    return int(value)


def _external(candidates):
    try:
        position = np.asarray(candidates.position, np.float32)
        heading = np.asarray(candidates.heading)
        valid = getattr(candidates, "valid", None)
    except AttributeError:
        raise InvalidPoseError("decide: candidates need .position (L, 3) and .heading (L,)") \
            from None
    n = len(position)
    if position.ndim != 2 or position.shape[1] != 3 or heading.shape != (n,) or n == 0:
        raise InvalidPoseError(f"decide: candidate positions {position.shape} and headings "
                               f"{heading.shape} must be (L, 3) and (L,)")
    if not np.all(np.isfinite(position)):
        raise InvalidPoseError("decide: a candidate position is not finite")
    if not np.issubdtype(heading.dtype, np.integer) or np.any((heading < 0) | (heading >= 4)):
        raise InvalidPoseError("decide: candidate headings must be indices 0..3")
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    if valid.shape != (n,):
        raise InvalidPoseError(f"decide: candidate validity must be ({n},)")
    return position, heading.astype(np.int32), valid
