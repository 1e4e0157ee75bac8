"""The policy's input layout, shared by the exporter's header check and the runtime."""

# The one definition: jaxmripp.observation re-exports these for the JAX side.
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
