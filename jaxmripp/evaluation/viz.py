"""Pictures: 3D episode renders, learning curves and evaluation plots (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import EngFormatter  # noqa: E402
import numpy as np  # noqa: E402

ROBOT_COLOURS = plt.get_cmap("tab10").colors


def save_figure(fig, path, tight: bool = True) -> Path:
    """Writes fig as a PNG (creating folders) and closes it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches=None if tight else "tight")
    plt.close(fig)
    return path


def draw_buildings(ax, height, alpha: float = 0.35) -> None:
    """Grey boxes for a (G, G) height map on a 3D axis in unit-cube coordinates."""
    height = np.asarray(height)
    size = height.shape[0]
    xs, ys = np.nonzero(height)
    if len(xs):
        ax.bar3d(xs / size, ys / size, 0, 1 / size, 1 / size, height[xs, ys] / size,
                 color="0.75", alpha=alpha, shade=True, linewidth=0)


def render_episode(path: str | Path, height, target_voxel, target_valid, discovered,
                   positions, active, radio_range: float, title: str = "") -> Path:
    """Saves a 3D picture: buildings, windows found (green) / missed (red), paths, radio links.

    height (G, G) voxels; target_voxel (T, 3); target_valid, discovered (T,);
    positions (T_steps + 1, N, 3) in the unit cube; active (T_steps, N).
    """
    height = np.asarray(height)
    size = height.shape[0]
    positions = np.asarray(positions)
    active = np.asarray(active)
    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    draw_buildings(ax, height)
    valid = np.asarray(target_valid)
    found = np.asarray(discovered) & valid
    centres = (np.asarray(target_voxel) + 0.5) / size
    for mask, colour, label in [(found, "tab:green", "window found"),
                                (valid & ~found, "tab:red", "window missed")]:
        if mask.any():
            ax.scatter(*centres[mask].T, s=6, c=colour, label=f"{label} ({mask.sum()})",
                       depthshade=False)
    steps = active.shape[0]
    for robot in range(positions.shape[1]):
        # A robot's path is its start plus every pose it actually flew to.
        keep = np.concatenate([[True], active[:, robot]])[: steps + 1]
        flown = positions[: steps + 1][keep, robot]
        colour = ROBOT_COLOURS[robot % len(ROBOT_COLOURS)]
        ax.plot(*flown.T, "-o", color=colour, markersize=2.5, linewidth=1.5,
                label=f"robot {robot}")
    final = positions[-1]
    for a in range(len(final)):
        for b in range(a + 1, len(final)):
            if np.linalg.norm(final[a] - final[b]) <= radio_range:
                ax.plot(*np.stack([final[a], final[b]]).T, ":", color="tab:blue", linewidth=1)
    ax.set(xlim=(0, 1), ylim=(0, 1), zlim=(0, 1), xlabel="x", ylabel="y", zlabel="z")
    ax.set_title(title or "episode")
    ax.legend(loc="upper left", fontsize=7)
    return save_figure(fig, path, tight=False)


def render_result(path, result, radio_range: float, title: str = "") -> Path:
    """Convenience for an unbatched `episode.EpisodeResult`."""
    world = result.final_state.world
    t = result.trajectory
    return render_episode(path, world.height, world.target_voxel, world.target_valid,
                          result.final_state.discovered, t.position, t.active, radio_range,
                          title)


def learning_curve(path, records: list[dict], keys=("discovered", "return")) -> Path:
    """Plots metrics.jsonl records against environment steps, one panel per key."""
    keys = [k for k in keys if any(k in r for r in records)]
    fig, axes = plt.subplots(1, max(len(keys), 1), figsize=(5 * max(len(keys), 1), 3.5))
    axes = np.atleast_1d(axes)
    for ax, key in zip(axes, keys):
        points = [(r["env_steps"], r[key]) for r in records if key in r]
        if points:
            x, y = zip(*points)
            ax.plot(x, y, "-o", markersize=3)
        ax.set(xlabel="agent steps (robot decisions)", ylabel=key, title=key)
        ax.xaxis.set_major_formatter(EngFormatter(sep=""))  # 150k: six-digit labels collide
        ax.grid(alpha=0.3)
    return save_figure(fig, path)


def discovery_curves(path, results: dict[str, dict]) -> Path:
    """% discovered against fraction of budget used, mean and std band per planner."""
    fig, ax = plt.subplots(figsize=(6, 4))
    grid = np.linspace(0, 1, 41)
    for name, r in results.items():
        curves = np.stack([np.interp(grid, b, d) for b, d in
                           zip(r["curve_budget"], r["curve_discovered"])])
        mean, std = curves.mean(axis=0), curves.std(axis=0)
        ax.plot(grid, mean, label=name)
        ax.fill_between(grid, mean - std, mean + std, alpha=0.2)
    ax.set(xlabel="fraction of team budget used", ylabel="% targets discovered")
    ax.grid(alpha=0.3)
    ax.legend()
    return save_figure(fig, path)
