"""jaxmripp: multi-robot informative path planning, trained end to end in JAX."""

__version__ = "0.1.0"
