"""The onboard planner of one robot: own map, own GPs, radio, candidates, decision.

One planning round, on every robot, in this order (the JAX env's order, `jaxmripp.sim.env`):

    planner.sense(position, heading, voxels, values, n_seen)   # where I am, what I saw
    radio.broadcast(planner.message())                          # waypoints, position, budget
    for data in radio.received(): planner.receive(data)         # robots within range
    radio.broadcast(planner.map_message())                      # with spec.share_maps only:
    for data in radio.received(): planner.receive_map(data)     # map deltas, merged
    decision = planner.decide()                                 # the chosen pose
    radio.broadcast(planner.intent_message())                   # its target (null: hover)
    for data in radio.received(): planner.receive_intent(data)  # their targets
    decision = planner.resolve()                                # the pose to fly, or a hold

`sense` charges the budget for the move just made, records the visited pose and the number
of windows seen from it, writes the observed voxels into the map and marks the robot's own
voxel FREE.
`receive` stores what a neighbour visited and where it is now. With `spec.share_maps`
(`jaxmripp.spec.sharing`), `map_message` sends every robot heard this round the voxels of
this robot's map it may lack (`sharing`; the size in bytes is kept in
`last_map_message_bytes`) and `receive_map` merges the delta addressed to this robot, so
that its map is the one the env's merge gives (with the target belief, the windows known,
which `sense` takes from the robot's classifier, travel as bits of the deltas); a robot that heard nobody may skip both.
`decide` feeds the GPs (the rule of `jaxmripp.spec.feeding`, in `feeding`), draws candidate
poses (`candidates`) or takes ones supplied by the caller, builds the policy's inputs on the
merged map (the rule of `jaxmripp.spec.layout`, in `observation`, with the view gain of
`jaxmripp.spec.view`, in `view`, the target belief of `jaxmripp.spec.belief`, in `belief`,
and the lookahead input, in `lookahead`, where the policy has them) and picks the next pose with the exported policy or the greedy rule of
`jaxmripp.evaluation.baselines.greedy_planner`. `resolve` applies the intent rule of
`jaxmripp.spec.flight`: if the chosen flight comes within d_c of the
flight announced by a lower-id robot heard, the robot holds -- it
stays where it is, is charged nothing, and the next `sense` gets the same pose. Inputs are
checked first (`validation`), so a rejected call changes nothing, and calls out of order
(`ROUND` in `exchange`) are refused. With a team key (`team_key`, `jaxmripp.runtime.auth`)
every broadcast is signed and unsigned, forged or replayed messages are refused.

Safety filter (`safety`): whatever picks the pose, it is chosen among candidates whose
straight flight is known free (every voxel it traverses is FREE in the robot's map, the
traversal rule of `jaxmripp.spec.grid`), whose flight keeps more than d_c from every robot
heard this round (closest approach, `flight`), inside the world and within the budget. If
none is left the robot hovers: the decision is its current pose, `hover` is True and
`reason` says why.

Differences from the JAX env, on purpose: the radio is single hop (the paper's; a relay
export is refused by nothing but still runs single hop, maps included), a robot with no safe
candidate hovers and tries again next round instead of being retired, and the utility GP is
always the robot's own (a shared training-time GP does not exist on a robot).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from jaxmripp.runtime import candidates as cands
from jaxmripp.runtime import belief, depth, flight, lookahead, observation, safety, validation
from jaxmripp.runtime.decision import Decision
from jaxmripp.runtime.errors import PlannerStateError
from jaxmripp.runtime.exchange import RadioExchange
from jaxmripp.runtime.feeding import FeedSchedule
from jaxmripp.runtime.gp import GaussianProcess
from jaxmripp.runtime.mapping import OccupancyMap, voxel_ahead
from jaxmripp.runtime.policy import NumpyPolicy
from jaxmripp.runtime.sharing import MapSharing
from jaxmripp.runtime import weights
from jaxmripp.spec.grid import FREE, HEADING_ANGLES, OCCUPIED
from jaxmripp.spec import layout
from jaxmripp.spec import sectors as sectors_spec
from jaxmripp.spec.layout import FEATURES

F32 = np.float32
COL = {name: i for i, name in enumerate(FEATURES)}
MODES = validation.MODES


class OnboardPlanner(RadioExchange):
    """One robot's planner; see the module doc for the call order."""

    def __init__(
        self,
        spec: weights.RuntimeSpec,
        robot_id: int,
        budget: float,
        team_size: int | None = None,
        policy: NumpyPolicy | None = None,
        mode: str | None = None,
        kappa: float = 1.0,
        lam: float = 0.0,
        facade_weight: float = 0.0,
        max_steps: int | None = None,
        seed: int | None = None,
        sectors: bool = False,
        team_key: bytes | None = None,
    ):
        """spec: from the export header; budget: this robot's share of the team budget;
        team_size: robot ids are 0 .. team_size - 1 (default: the trained team size);
        mode: "policy" (needs `policy`), "greedy" (score = utility mean + kappa * std -
        lam * communication mean), "nbv" (next-best view: `jaxmripp.spec.layout.nbv_score`
        with `facade_weight`) or "random" (uniform among the safe candidates); max_steps:
        the episode length the policy's step feature is normalised by (default: the
        export's); seed: candidate sampling (default: id); sectors: keep to this robot's
        sector of the world, seen from the team's first pad `spec.start`, while it has
        unknown views there, if the radio range is short enough for the rule
        (`jaxmripp.spec.sectors`, as `eval.sectors` in the JAX sweeps); team_key: the
        team's secret (bytes, `jaxmripp.runtime.auth`): every message is then signed and
        only messages signed with it are taken (`rejected_messages` counts the others).
        The obstacle rule is the spec's `flight`, from the export."""
        team_size = spec.team_size if team_size is None else int(team_size)
        mode = mode or ("policy" if policy is not None else "greedy")
        validation.settings(mode, policy is not None, robot_id, team_size, budget,
                            spec.flight)
        self.spec = spec
        self.id = int(robot_id)
        self.team_size = team_size
        self.policy = policy
        self.mode = mode
        self.kappa, self.lam = float(kappa), float(lam)
        self.facade_weight = float(facade_weight)
        self.sectors = bool(sectors)
        self.max_steps = spec.max_steps if max_steps is None else int(max_steps)
        self.rng = np.random.default_rng(self.id if seed is None else seed)

        self.map = OccupancyMap(spec.size)
        self.sharing = MapSharing(self.id, self.map, windows=spec.belief_features)
        self._init_radio(team_key)
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
        self._command: tuple[np.ndarray, np.ndarray] | None = None  # (from, to) of last move
        self._pending: Decision | None = None  # decided, not resolved yet
        self._map_sent = self._decided = False  # this round's map message / decision

    @classmethod
    def load(cls, export: str | Path, robot_id: int, budget: float, **kwargs) -> "OnboardPlanner":
        """A planner driven by an exported policy (directory or policy.json); kwargs as
        the constructor's (team_key: the team's radio key)."""
        exported = weights.load(export)
        return cls(exported.spec, robot_id, budget, policy=exported.policy, **kwargs)

    def _peer_ids(self):
        return [j for j in range(self.team_size) if j != self.id]

    # -----------------------------------------------------------------------------------
    # Inputs

    def sense(self, position, heading, voxels, values, n_seen: int, blocked: bool = False,
              windows=None) -> None:
        """Where the robot is now and what its camera saw from there.

        position (3,) in the unit cube and heading index 0..3 (+x, +y, -x, -y): the pose
        reached (short of the commanded one if `blocked`; the same pose after a hover or a
        hold); voxels: observed voxels as flat C-order indices into (G, G, G) (G^3 marks
        "not observed" and is skipped) or as (K, 3) integer coordinates; values: their
        codes (0 free, 2 occupied); n_seen: windows seen from this pose. blocked: the last
        move was stopped by an
        obstacle; the voxel ahead of the stop on the commanded segment is then mapped
        occupied. windows: the voxels among these that the robot's classifier reports as
        windows, as flat indices or (K, 3) coordinates (each mapped OCCUPIED once the call
        is done); they are what the target belief counts (`belief`).
        """
        position = validation.position(position, "sense: position")
        heading = validation.heading(heading, "sense: heading")
        flat, codes = validation.observed(voxels, values, self.spec.size)
        n_seen = validation.n_seen(n_seen)
        windows = validation.windows(windows, flat, codes, self.map.codes, self.spec.size)

        first = self.position is None
        moved = first or self._command is not None  # a hover or a hold is not a visit
        if not first:
            self.step += 1
            if self._command is not None:
                self._charge(position, heading)
                if blocked:
                    start, end = self._command
                    voxel = voxel_ahead(start, end, position, self.map.codes, self.spec.size,
                                        self.spec.shell[1])
                    if voxel is not None:
                        self.map.mark_occupied(voxel)
        self.position, self.heading = position, heading
        self.map.update(flat, codes)
        self.map.mark_windows(windows)
        self.map.mark_own_voxel(position)
        self.sharing.note_sensed(self.step)
        if moved:
            self.history_pose.append(np.append(position, HEADING_ANGLES[heading]).astype(F32))
            self.history_utility.append(F32(n_seen) / F32(self.spec.utility_norm))
        self._command = None
        self._pending, self.intents = None, {}
        self._map_sent = self._decided = False
        self.contacts = {}  # positions heard are good for this round only

    def sense_depth(self, position, heading, images, camera, frame, n_seen: int,
                    blocked: bool = False, windows=None) -> None:
        """`sense` from depth images instead of voxel lists (`jaxmripp.runtime.depth`):
        images [(depth (H, W) metres, camera position (3,) metres, rotation (3, 3) camera
        -> world), ...] taken at this pose;
        camera: `DepthCamera`; frame: the `GridFrame` placing the unit cube in metres.
        Voxels this map holds OCCUPIED stay so (a static world). windows: as `sense`'s, as
        (K, 3) voxel coordinates; those whose voxel the images leave unmapped OCCUPIED (a
        sighting the depth pixels missed) are left out."""
        flat, codes = depth.observe_many(images, camera, frame, self.spec.size)
        keep = ~((codes == FREE) & (self.map.codes[flat] == OCCUPIED))
        flat, codes = flat[keep], codes[keep]
        if windows is not None:
            windows = validation.windows(windows, flat, codes, self.map.codes, self.spec.size,
                                         drop=True)
        self.sense(position, heading, flat, codes, n_seen, blocked=blocked, windows=windows)

    # -----------------------------------------------------------------------------------
    # Decision

    def decide(self, candidates: Any = None, tie_break: np.ndarray | None = None,
               mode: str | None = None) -> Decision:
        """The next pose. candidates: optional externally supplied poses (an object with
        `position` (L, 3), `heading` (L,) and optionally `valid` (L,)) instead of sampling
        them; tie_break: (L,) added to greedy scores (jaxmripp's greedy adds 1e-5 x uniform
        noise; pass the same to reproduce its choices). Then `intent_message`,
        `receive_intent` and `resolve` give the pose to fly."""
        self._require_sensed("decide")
        mode = validation.decide_mode(mode or self.mode, self.policy is not None)
        external = validation.external(candidates) if candidates is not None else None
        n = self.spec.n_candidates if external is None else len(external[0])
        tie_break = validation.tie_break(tie_break, n)

        self.feed_gps()
        stats: dict = {}
        c = self._sample(stats) if external is None else self._supplied(*external)
        features, robot_state = self.observe(c, ahead=mode == "policy")
        safe, why = safety.check(c, self.position, self.budget_left, self.map,
                                 self._known_robots(), self.spec)
        done = self.step >= self.max_steps
        mask = c.valid & safe & (not done)
        if self.sectors and sectors_spec.applies(self.spec.radio_range):
            mask = sectors_spec.offered(mask, features, c.position,
                                        np.asarray(self.spec.start, F32), self.id, self.team_size)
        scores = self._scores(mode, features, mask, robot_state, tie_break)

        if not mask.any():
            reason = ("hover: step limit reached" if done else
                      safety.hover_reason(c, why, stats, self.budget_left, self.spec))
            decision = self._hover(mode, reason, scores, mask, safe, features, robot_state, c)
        else:
            index = int(layout.masked_argmax(scores, mask))
            position, heading = c.position[index], int(c.heading[index])
            self._command = (self.position.copy(), position.copy())
            decision = Decision(
                pose=np.append(position, HEADING_ANGLES[heading]).astype(F32),
                position=position, heading=heading, index=index, hover=False, reason=mode,
                mode=mode, scores=scores, mask=mask, safe=safe, features=features,
                robot_state=robot_state, candidates=c)
        self._pending, self.intents, self._decided = decision, {}, True
        return decision

    def resolve(self) -> Decision:
        """The decision to fly, after the intents heard (`receive_intent`): `decide`'s, or
        a hold -- the current pose, `hover` True, `yields_to` and `reason` naming the
        robot -- when the chosen flight's closest approach to the announced flight of a
        lower-id robot heard is <= d_c."""
        decision = self._require_decided("resolve")
        self._pending = None
        if decision.hover:
            return decision
        conflict = flight.yields_to(self.id, self.position, decision.position, self.intents,
                                    self.spec.collision_distance)
        if conflict is None:
            return decision
        sender, gap = conflict
        self._command = None  # hold: no move, nothing charged, no visit
        reason = (f"hold: yields to robot {sender} (its announced flight comes within "
                  f"{gap:.3g} of ours, d_c = {self.spec.collision_distance:g})")
        return dataclasses.replace(
            decision, pose=np.append(self.position, HEADING_ANGLES[self.heading]).astype(F32),
            position=self.position.copy(), heading=self.heading, index=-1, hover=True,
            reason=reason, yields_to=sender)

    def feed_gps(self) -> None:
        """Feeds this round's pending poses into the GPs (`decide` does it first thing)."""
        self.feeding.feed(self.utility_gp, self.comm_gp, self.history_pose,
                          self.history_utility, self.peer_pose, self.peer_utility)

    def observe(self, c: cands.Candidates, ahead_uniforms: np.ndarray | None = None,
                ahead: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The policy's inputs (features (L, F), robot_state (S,)) for candidates `c` from
        the robot's current state and GPs, without feeding or deciding anything. With the
        lookahead input (`spec.ahead_branches` > 0, unless `ahead` is False: the other
        modes do not read it) its draws take `ahead_uniforms` (`lookahead.draw_shape`), by
        default the robot's generator's next ones."""
        self._require_sensed("observe")
        heard = self._known_robots()
        rates = None if not self.spec.belief_features else belief.facade_rates(
            self.map, self.spec.belief_strength, self.spec.belief_prior, self.spec.gain_facade)
        features = observation.candidate_features(
            c, self.position, self.budget_left, self.budget_initial, self.spec.shell[1],
            self.utility_gp, self.comm_gp, self.map, heard, self.spec.gain, rates)
        if self.spec.ahead_branches and ahead:
            if ahead_uniforms is None:
                ahead_uniforms = self.rng.random(lookahead.draw_shape(self.spec), F32)
            mask = c.valid & (self.step < self.max_steps)
            values = lookahead.ahead_rates(ahead_uniforms, features, mask, c,
                                           self.budget_left, self.map, heard, self.spec, rates)
            features = np.concatenate([features, values[:, None]], axis=1)
        state = observation.robot_state(self.position, self.heading, self.budget_left,
                                        self.budget_initial, self.step, self.max_steps)
        return features, state

    # -----------------------------------------------------------------------------------
    # Internals

    def _require_sensed(self, what):
        if self.position is None:
            raise PlannerStateError(f"{what}: call sense() with the robot's first pose first")

    def _require_decided(self, what) -> Decision:
        if self._pending is None:
            raise PlannerStateError(f"{what}: call decide() first (once per round, after "
                                    "sense)")
        return self._pending

    def _charge(self, position: np.ndarray, heading: int) -> None:
        """Budget for the move just made: distance as flown (to where the robot really is,
        short of the command if blocked) plus the turn cost on a heading change."""
        charge = np.linalg.norm(position - self.position).astype(F32) \
            + F32(self.spec.turn_cost) * F32(heading != self.heading)
        self.budget_left = F32(max(self.budget_left - charge, F32(0.0)))

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
        if mode == "random":
            return self.rng.random(len(mask)).astype(F32)
        if mode == "nbv":
            return layout.nbv_score(features, self.facade_weight).astype(F32)
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
