"""Checks of everything a caller hands the onboard planner, before any state changes.

Each function either returns the value converted to the planner's types or raises one of
`jaxmripp.runtime.errors` (InvalidPoseError for poses and sensing, ValueError for
settings) with a one-line message. They are separate from the planner so that its methods
read as the planning round, and so that the planner's guarantee -- a rejected input
leaves it exactly as it was -- rests on validating first and mutating second.
"""

from __future__ import annotations

import math

import numpy as np

from jaxmripp.runtime.errors import InvalidPoseError
from jaxmripp.spec.grid import N_HEADINGS, OCCUPIED

F32 = np.float32
MODES = ("policy", "greedy", "nbv", "random")


def settings(mode: str, has_policy: bool, robot_id: int, team_size: int, budget: float,
             flight: str) -> None:
    """The planner's constructor arguments and the spec's safety rules (ValueError names
    the argument)."""
    if mode not in MODES:
        raise ValueError(f"mode: got {mode!r}; allowed: {', '.join(MODES)}")
    if mode == "policy" and not has_policy:
        raise ValueError("mode 'policy' needs a policy (OnboardPlanner.load an export)")
    if not 0 <= int(robot_id) < team_size:
        raise ValueError(f"robot_id: got {robot_id}; allowed: 0 .. {team_size - 1}")
    if not (math.isfinite(budget) and budget > 0):
        raise ValueError(f"budget: got {budget}; allowed: a positive number")
    if flight != "known_free":
        raise ValueError(f"spec.flight: got {flight!r}; the onboard runtime flies known_free "
                         "only")


def decide_mode(mode: str, has_policy: bool) -> str:
    """The mode of one `decide` call: the rules work without weights, policy needs
    them."""
    if mode not in MODES or (mode == "policy" and not has_policy):
        raise ValueError(f"mode: got {mode!r}; allowed: greedy, nbv, random" +
                         (", policy" if has_policy else ""))
    return mode


def position(value, name: str) -> np.ndarray:
    """(3,) float32 inside the unit cube (float64 first, so NaN and range are judged on
    the caller's numbers rather than on their float32 rounding)."""
    try:
        result = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidPoseError(f"{name} must be 3 numbers, got {value!r}") from None
    if result.shape != (3,):
        raise InvalidPoseError(f"{name} must be 3 numbers, got shape {result.shape}")
    if not np.all(np.isfinite(result)):
        raise InvalidPoseError(f"{name} is not finite: {result.tolist()}")
    if np.any((result < 0.0) | (result > 1.0)):
        raise InvalidPoseError(f"{name} {result.tolist()} lies outside the unit cube")
    return result.astype(F32)


def heading(value, name: str) -> int:
    """A heading index 0..3; bools are refused (True would silently mean +y)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or not 0 <= int(value) < N_HEADINGS:
        raise InvalidPoseError(f"{name} must be a heading index 0..3, got {value!r}")
    return int(value)


def n_seen(value) -> int:
    """The number of windows seen: a non-negative integer (it becomes a GP target)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or value < 0:
        raise InvalidPoseError(f"sense: n_seen must be a non-negative integer, got {value!r}")
    return int(value)


def observed(voxels, values, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Observed voxels (flat indices, G^3 = "not observed", or (K, 3) coordinates) and
    their codes -> (flat int64 indices, int8 codes) of the observed ones only.

    G^3 is accepted as padding because the JAX camera (`jaxmripp.sim.sensing.cast`)
    returns fixed-size arrays padded with it; a robot can pass its output unchanged.
    """
    g = size
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


def windows(value, flat: np.ndarray, codes: np.ndarray, known: np.ndarray,
            size: int, drop: bool = False) -> np.ndarray:
    """The window voxels of a `sense` call (None: none; flat indices or (K, 3)
    coordinates) -> flat int64 indices. A window is a building voxel the camera saw: each
    must be OCCUPIED once the call's voxels `flat` / `codes` are written over the map's
    codes `known` (the last write of a voxel wins, as in the map); with `drop` the others
    are left out instead of refused."""
    if value is None:
        return np.zeros(0, np.int64)
    g = size
    voxels = np.asarray(value)
    if voxels.ndim == 2 and voxels.shape[1] == 3:
        if not np.issubdtype(voxels.dtype, np.integer) or np.any((voxels < 0) | (voxels >= g)):
            raise InvalidPoseError(f"sense: window coordinates must be integers in 0..{g - 1}")
        voxels = (voxels[:, 0] * g + voxels[:, 1]) * g + voxels[:, 2]
    if voxels.ndim != 1 or (voxels.size and (not np.issubdtype(voxels.dtype, np.integer)
                                             or voxels.min() < 0 or voxels.max() >= g ** 3)):
        raise InvalidPoseError(f"sense: windows must be a 1-D array of flat voxel indices in "
                               f"0..{g ** 3 - 1} (or (K, 3) coordinates)")
    voxels = voxels.astype(np.int64)
    after = known[voxels].copy()
    order = np.argsort(flat, kind="stable")  # equal voxels keep their order: last = last
    last = np.searchsorted(flat[order], voxels, side="right") - 1
    written = (last >= 0) & (np.append(flat[order], -1)[last] == voxels)
    after[written] = codes[order][last[written]]
    if drop:
        return voxels[after == OCCUPIED]
    if np.any(after != OCCUPIED):
        x, y, z = np.unravel_index(voxels[after != OCCUPIED][0], (g, g, g))
        raise InvalidPoseError(f"sense: window voxel ({x}, {y}, {z}) is not mapped occupied; "
                               "a window must be a building voxel seen OCCUPIED")
    return voxels


def external(candidates) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Caller-supplied candidates (any object with .position, .heading, optional .valid)
    -> (position (L, 3) float32, heading (L,) int32, valid (L,) bool)."""
    try:
        where = np.asarray(candidates.position, np.float32)
        headings = np.asarray(candidates.heading)
        valid = getattr(candidates, "valid", None)
    except AttributeError:
        raise InvalidPoseError("decide: candidates need .position (L, 3) and .heading (L,)") \
            from None
    n = len(where)
    if where.ndim != 2 or where.shape[1] != 3 or headings.shape != (n,) or n == 0:
        raise InvalidPoseError(f"decide: candidate positions {where.shape} and headings "
                               f"{headings.shape} must be (L, 3) and (L,)")
    if not np.all(np.isfinite(where)):
        raise InvalidPoseError("decide: a candidate position is not finite")
    if not np.issubdtype(headings.dtype, np.integer) \
            or np.any((headings < 0) | (headings >= N_HEADINGS)):
        raise InvalidPoseError("decide: candidate headings must be indices 0..3")
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    if valid.shape != (n,):
        raise InvalidPoseError(f"decide: candidate validity must be ({n},)")
    return where, headings.astype(np.int32), valid


def tie_break(value, n: int) -> np.ndarray | None:
    """Optional (L,) finite float32 noise added to greedy scores."""
    if value is None:
        return None
    value = np.asarray(value, F32)
    if value.shape != (n,) or not np.all(np.isfinite(value)):
        raise InvalidPoseError(f"decide: tie_break must be ({n},) finite numbers")
    return value
