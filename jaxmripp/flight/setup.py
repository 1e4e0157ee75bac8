"""Loading a team for the physics missions: an export (or a config, for the policy-free
planners), the world it was trained for, and the figures a mission reports."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from jaxmripp.flight import city as citymod
from jaxmripp.runtime import weights as fmt


@dataclasses.dataclass(frozen=True)
class Team:
    spec: fmt.RuntimeSpec
    exported: fmt.ExportedPolicy | None
    world: object  # jaxmripp.config.WorldConfig of the cities to fly in
    pad_spacing: float


def load_team(export: Path) -> Team:
    """The exported policy in `export` (its config.yaml beside policy.json, if any, gives
    the world; else the default config's world at the export's size)."""
    from jaxmripp import config as cfgmod

    exported = fmt.load(export)
    directory = Path(export) if Path(export).is_dir() else Path(export).parent
    cfg = cfgmod.load(directory / "config.yaml" if (directory / "config.yaml").exists()
                      else None)
    world = dataclasses.replace(cfg.world, size=exported.spec.size, layout="random",
                                targets=(cfg.world.targets[1],) * 2)
    spacing = exported.header["config"]["robots"].get("pad_spacing", cfg.robots.pad_spacing)
    return Team(exported.spec, exported, world, float(spacing))


def city(team: Team, seed: int, frame: citymod.CityFrame) -> citymod.City:
    return citymod.generate(seed, team.world, frame)


def figures(result) -> dict:
    """The JSON figures of one mission."""
    return {
        "planner": result.planner, "pct": round(result.pct, 3), "windows": result.windows,
        "crashes": len(result.crashes),
        "crash_list": [dataclasses.asdict(c) for c in result.crashes[:20]],
        "rounds": result.rounds, "late_arrivals": result.late_arrivals,
        "false_free_voxels": result.false_free,
        "sim_seconds": round(result.sim_seconds, 2),
        "wall_seconds": round(result.wall_seconds, 2),
        "sim_realtime_factor": round(result.sim_seconds / result.wall_seconds, 2),
        "decision_ms_median": round(float(np.median(result.decision_ms)), 3),
        "sense_ms_median": round(float(np.median(result.sense_ms)), 3),
        "max_speed": round(result.max_speed, 3), "track_error_m": round(result.track_error, 4),
    }
