"""What a team flown by the onboard runtime needs around its planners: the exported
policy with the world it was trained for (`load_team`), the take-off pads and a radio that
delivers each broadcast to the robots within range (NumPy)."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from jaxmripp.runtime import weights as fmt

if TYPE_CHECKING:
    from jaxmripp.config import WorldConfig


@dataclasses.dataclass(frozen=True)
class Team:
    spec: fmt.RuntimeSpec
    exported: fmt.ExportedPolicy
    world: WorldConfig  # the cities to fly in
    pad_spacing: float


def load_team(export: Path, footprints: tuple[int, int] | None = None,
              radio_range: float | None = None) -> Team:
    """The exported policy in `export` and its world: config.yaml beside policy.json if
    there is one (else the default config's world) at the export's size, random layout
    (the test layout), the largest window count; footprints (lo, hi): building sides drawn
    from lo .. hi voxels instead of the trained world's squares; radio_range: the team's
    radio range (the config's rules for radio.range) instead of the export's `radio.range`."""
    from jaxmripp import config as cfgmod

    exported = fmt.load(export)
    directory = Path(export) if Path(export).is_dir() else Path(export).parent
    cfg = cfgmod.load(directory / "config.yaml" if (directory / "config.yaml").exists()
                      else None)
    world = {"size": exported.spec.size, "layout": "random",
             "targets": [cfg.world.targets[1]] * 2}
    if footprints is not None:  # equal sides: the square footprints of the trained world
        lo, hi = footprints
        world.update(footprint_min=0 if lo == hi else lo, footprint=hi)
    radio = {} if radio_range is None else {"radio": {"range": radio_range}}
    checked = cfgmod.from_dict({"world": world} | radio, base=cfg)  # the config's rules
    spacing = exported.header["config"]["robots"].get("pad_spacing", cfg.robots.pad_spacing)
    spec = exported.spec
    if radio_range is not None:
        spec = dataclasses.replace(spec, radio_range=checked.radio.range)
    return Team(spec, exported, checked.world, float(spacing))


DEFAULT_FOOTPRINTS = (2, 5)  # building sides in voxels (2.4 m to 6 m in the default box)


def parse_footprints(text: str) -> tuple[int, int]:
    """"LO,HI" -> (LO, HI): building sides drawn from LO .. HI voxels (1 <= LO <= HI)."""
    try:
        lo, hi = (int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"footprints: got {text!r}; allowed: LO,HI (integers, "
                         "1 <= LO <= HI), e.g. 2,5") from None
    if not 1 <= lo <= hi:
        raise ValueError(f"footprints: got {text!r}; allowed: 1 <= LO <= HI")
    return lo, hi


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
