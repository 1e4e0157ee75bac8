"""What one decision of the onboard planner (`jaxmripp.runtime.planner`) returns."""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxmripp.runtime import candidates as cands


@dataclasses.dataclass(frozen=True)
class Decision:
    """The outcome of one `decide` (or `resolve`) call."""

    pose: np.ndarray  # (4,) float32 next waypoint (x, y, z, heading angle); current if hover
    position: np.ndarray  # (3,) float32
    heading: int  # heading index of `pose`
    index: int  # chosen candidate, -1 when hovering
    hover: bool
    reason: str  # the mode that chose (one of MODES), or why it hovers
    mode: str
    scores: np.ndarray  # (L,) policy logits (infeasible floored) or greedy scores
    mask: np.ndarray  # (L,) bool candidates the rule could pick (offered, safe, in sector)
    safe: np.ndarray  # (L,) bool passed the safety filter
    # (L, F) inputs, layout FEATURES (+ the belief input where the export has it, + the
    # lookahead input in policy mode)
    features: np.ndarray
    robot_state: np.ndarray  # (S,) policy input, layout ROBOT_STATE
    candidates: cands.Candidates
    yields_to: int | None = None  # a hold (`resolve`): the robot whose flight goes first
