"""The policy's input columns: written by the environment, read by the policy, checked by
the exporter and rebuilt by the runtime.

FEATURES per candidate: dx, dy, dz offset from the robot divided by the largest candidate
distance; x, y, z absolute position; one-hot heading; posterior mean and standard
deviation of the utility and communication GPs; path cost; budget left after the move as
a fraction of the initial budget.
ROBOT_STATE: position, one-hot heading, budget left (fraction), step / T_max.
A centralised critic also reads every robot's ROBOT_STATE (robot-major) followed by the
N_GLOBAL_EXTRA team values: the discovered fraction and the mean budget left (fraction).
"""

FEATURES = (
    "dx", "dy", "dz", "x", "y", "z",
    "heading_0", "heading_1", "heading_2", "heading_3",
    "utility_mean", "utility_std", "comm_mean", "comm_std",
    "cost", "budget_after",
)  # fmt: skip
ROBOT_STATE = (
    "x", "y", "z",
    "heading_0", "heading_1", "heading_2", "heading_3",
    "budget_left", "step",
)  # fmt: skip
N_GLOBAL_EXTRA = 2
