"""Onboard planner runtime: NumPy only, never imports jax or flax (it runs on drones)."""

from jaxmripp.runtime.policy import NumpyPolicy

__all__ = ["NumpyPolicy"]
