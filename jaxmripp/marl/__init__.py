"""The environment as a JaxMARL `MultiAgentEnv` (optional extra `marl`: pip install -e '.[marl]').

`MRIPPEnv` wraps `jaxmripp.sim.env` unchanged, so JaxMARL's wrappers and baselines (IPPO,
MAPPO, `LogWrapper`) run on it. docs/marl.md shows its use.
"""

try:
    import jaxmarl.environments.multi_agent_env  # noqa: F401
except ImportError as err:  # the extra is not installed
    raise ImportError(f"jaxmripp.marl needs the package jaxmarl ({err}); install it with "
                      "pip install -e '.[marl]'") from err

from jaxmripp.marl.env import MRIPPEnv, flat_observation, load_config

__all__ = ["MRIPPEnv", "flat_observation", "load_config"]
