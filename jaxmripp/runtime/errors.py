"""Errors of the onboard runtime: one class per kind of bad input, one-line messages.

Every public entry point validates its inputs completely before it changes any state, so
a caught error leaves the planner exactly as it was (no half-applied update, no action).
"""

from __future__ import annotations


class RuntimeInputError(ValueError):
    """Base class: some input to the onboard runtime is unusable."""

    def __init__(self, message: str):
        # One line, whatever the caller interpolated.
        super().__init__(" ".join(str(message).split()))


class WeightsFormatError(RuntimeInputError):
    """An export file is of another format or format version, or lacks a field."""


class CorruptWeightsError(RuntimeInputError):
    """An export file is truncated, unreadable or does not match its recorded hash."""


class ProtocolVersionError(RuntimeInputError):
    """A radio message speaks a protocol version this runtime does not understand."""


class MessageError(RuntimeInputError):
    """A radio message is malformed (not JSON, missing fields, bad values) or, on a team
    with a key, unsigned, forged or stale (`jaxmripp.runtime.auth.REASONS`)."""

    def __init__(self, message: str, reason: str = "malformed"):
        super().__init__(message)
        self.reason = reason


class TeamKeyError(RuntimeInputError):
    """A team key for signing radio messages is not bytes, or too short."""


class InvalidPoseError(RuntimeInputError):
    """A pose or sensing result is not finite, outside the world, or badly shaped."""


class PlannerStateError(RuntimeInputError):
    """A call arrived out of order (e.g. `decide` before the first `sense`)."""
