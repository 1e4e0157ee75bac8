"""What a team flown by the onboard runtime needs around the planners, in NumPy: its
take-off pads and a radio that delivers each broadcast to the robots within range."""

from __future__ import annotations

import math

import numpy as np


def pads(start, count: int, spacing: float) -> np.ndarray:
    """Take-off pads (`jaxmripp.spec.flight`): start + spacing (i mod m, 0, i div m),
    m = ceil(sqrt(N)); the JAX side is `jaxmripp.sim.flight.pads`."""
    side = math.ceil(math.sqrt(count))
    i = np.arange(count)
    offset = np.stack([i % side, np.zeros_like(i), i // side], axis=-1).astype(np.float32)
    return (np.asarray(start, np.float32) + np.float32(spacing) * offset).astype(np.float32)


def exchange(outbox: list, position: np.ndarray, radio_range: float, deliver) -> None:
    """Delivers every robot's broadcast to the robots within radio range."""
    gap = np.linalg.norm(position[:, None] - position[None], axis=-1)
    for i in range(len(outbox)):
        for j, data in enumerate(outbox):
            if j != i and gap[i, j] <= radio_range:
                deliver(i, data)
