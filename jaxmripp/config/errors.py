"""The one error configuration problems raise, and how values appear in it."""

from __future__ import annotations

from typing import Any


class ConfigError(ValueError):
    """A configuration value is unknown, mistyped or out of range."""


def shown(value: Any) -> Any:
    """A value as messages and YAML show it: lists for tuples."""
    return list(value) if isinstance(value, tuple) else value
