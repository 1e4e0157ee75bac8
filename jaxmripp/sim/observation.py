"""What one robot sees at one step: the data contract between the env and the policy.

The env fills an `Observation` per robot; the policy reads one robot's observation
(callers `vmap` over robots and environments, so every field may carry leading batch
axes). Only array-level libraries are imported here so that any module can depend on it.

Shapes (L candidates, F = len(FEATURES), S = len(ROBOT_STATE), N robots):
    features      (..., L, F)        float32, columns in FEATURES order
    mask          (..., L)           bool, True = feasible candidate
    robot_state   (..., S)           float32, columns in ROBOT_STATE order
    global_state  (..., N * S + 2)   float32, every robot's robot_state (robot-major),
                                     then the discovered fraction and the mean fraction
                                     of budget left (input of a centralised critic)
"""

from __future__ import annotations

import flax.struct
import jax

# The layout is defined once, next to the exported file format, in the NumPy-only runtime
# (which must not import this module). FEATURES per candidate: dx, dy, dz offset from the
# robot; x, y, z absolute position; one-hot heading; posterior mean and standard deviation
# of the utility and communication GPs; path cost; budget left after the move.
# ROBOT_STATE: position, one-hot heading, budget left, step counter.
from jaxmripp.spec.layout import FEATURES, ROBOT_STATE  # noqa: E402

N_FEATURES = len(FEATURES)  # F = 16
N_ROBOT_STATE = len(ROBOT_STATE)  # S = 9
N_GLOBAL_EXTRA = 2  # discovered fraction, mean budget left fraction


def global_state_size(robots: int) -> int:
    """Length of `Observation.global_state` for a team of `robots`."""
    return robots * N_ROBOT_STATE + N_GLOBAL_EXTRA


@flax.struct.dataclass
class Observation:
    features: jax.Array  # (..., L, F) float32 per-candidate features, layout FEATURES
    mask: jax.Array  # (..., L) bool, True = feasible candidate
    robot_state: jax.Array  # (..., S) float32, layout ROBOT_STATE
    global_state: jax.Array  # (..., N*S + 2) float32, for a centralised critic
