"""Plots of evaluation sweeps: discovery curves, team-size scaling, maps of the windows
missed, episode pictures, GIFs.

Inputs are `cells.ShapeRun`s (NumPy arrays); nothing here imports JAX.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib import animation  # noqa: E402

from jaxmripp.evaluation import viz  # noqa: E402
from jaxmripp.spec.grid import HEADING_NAMES, HEADING_VECTORS  # noqa: E402


def discovery_vs_budget(path, runs: dict, title: str = "", points: int = 41) -> Path:
    """% targets discovered against the fraction of the team budget used: mean and a
    +-1 std band per planner. runs: {planner: ShapeRun} of one shape."""
    fig, ax = plt.subplots(figsize=(6, 4))
    grid = np.linspace(0.0, 1.0, points)
    for name, r in runs.items():
        # Budget use is non-decreasing; after the last move a curve stays flat.
        curves = np.stack([np.interp(grid, b, d) for b, d in
                           zip(r.curve_budget, r.curve_discovered)])
        mean, std = curves.mean(axis=0), curves.std(axis=0)
        line, = ax.plot(grid, mean, label=name)
        ax.fill_between(grid, mean - std, mean + std, alpha=0.15, color=line.get_color())
    ax.set(xlabel="fraction of team budget used", ylabel="% targets discovered",
           title=title or None)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return viz.save_figure(fig, path)


def discovery_vs_team_size(path, runs: list) -> Path:
    """Mean +- std % discovered against N, one panel per world size G, one line per
    planner (and radio range / budget when the sweep has several)."""
    sizes = sorted({r.shape.size for r in runs})
    fig, axes = plt.subplots(1, len(sizes), figsize=(4.5 * len(sizes), 3.8), squeeze=False)
    several = len({(r.shape.radio_range, r.shape.budget) for r in runs}) > 1
    for ax, size in zip(axes[0], sizes):
        lines: dict = {}
        for r in runs:
            if r.shape.size != size:
                continue
            label = r.planner + (f" (rho {r.shape.radio_range:g}, B {r.shape.budget:g})"
                                 if several else "")
            lines.setdefault(label, []).append((r.shape.n_robots, r.discovered.mean(),
                                                r.discovered.std(ddof=1) if len(r.discovered) > 1 else 0.0))
        for label, pts in lines.items():
            n, mean, std = map(np.asarray, zip(*sorted(pts)))
            ax.errorbar(n, mean, yerr=std, marker="o", capsize=3, label=label)
        ax.set(xlabel="robots N", ylabel="% targets discovered", title=f"G = {size}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    return viz.save_figure(fig, path)


# Regions of the missed-window maps, in unit-cube coordinates: a window this close to the
# world's side faces a street the robots reach along the world's edge, one this low is
# seen only from low flights between buildings.
EDGE_STRIP = 0.05
LOW_WINDOW = 0.25
MAP_COLUMNS = 6  # panels per row of a missed-window map


# The horizontal directions a facade can face, as (label, dx, dy) on the voxel grid: the
# robots' headings.
FACINGS = tuple((name, int(v[0]), int(v[1])) for name, v in zip(HEADING_NAMES, HEADING_VECTORS))


def window_facing(height: np.ndarray, voxel: np.ndarray) -> np.ndarray:
    """Column heights (G, G) and window voxels (M, 3) -> (M, len(FACINGS)) bool: the
    directions each window's facade faces, those whose neighbouring column inside the
    grid is free at the window's height (a corner window faces two)."""
    size = height.shape[-1]
    x, y, z = (np.asarray(voxel)[:, a] for a in range(3))
    faces = []
    for _, dx, dy in FACINGS:
        nx, ny = x + dx, y + dy
        inside = (nx >= 0) & (nx < size) & (ny >= 0) & (ny < size)
        beside = height[np.clip(nx, 0, size - 1), np.clip(ny, 0, size - 1)]
        faces.append(inside & (beside <= z))
    return np.stack(faces, axis=-1).reshape(len(x), len(FACINGS))


def missed_windows(run) -> tuple[np.ndarray, dict[str, int]]:
    """The windows a ShapeRun's episodes never found, pooled over its episodes: their
    centres (M, 3) in the unit cube and counts {"windows", "missed", "edge", "low"}
    (missed within EDGE_STRIP of the world's side, below LOW_WINDOW) plus, per FACINGS
    label, the missed windows away from the side (the interior) facing that way."""
    s = run.snapshot
    size = s.height.shape[-1]
    valid = np.asarray(s.target_valid, bool)
    missed = valid & (np.asarray(s.found_at) < 0)
    voxel = np.asarray(s.target_voxel)
    faces = np.concatenate([window_facing(np.asarray(h), v[m])
                            for h, v, m in zip(s.height, voxel, missed)])
    centres = (voxel[missed] + 0.5) / size
    side = np.minimum(np.minimum(centres[:, 0], 1 - centres[:, 0]),
                      np.minimum(centres[:, 1], 1 - centres[:, 1]))
    interior = faces[side >= EDGE_STRIP]
    counts = {"windows": int(valid.sum()), "missed": int(missed.sum()),
              "edge": int((side < EDGE_STRIP).sum()),
              "low": int((centres[:, 2] < LOW_WINDOW).sum())}
    counts.update({label: int(interior[:, k].sum()) for k, (label, _, _) in enumerate(FACINGS)})
    return centres, counts


def missed_map(path, runs: list, title: str = "") -> Path:
    """Top-down maps of the windows never found, pooled over the episodes (the same
    worlds for every run of a sweep), one panel per run (planner and radio range),
    coloured by height; each panel's title counts them by region (`missed_windows`)."""
    columns = min(len(runs), MAP_COLUMNS)
    rows = -(-len(runs) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.6 * columns, 4.4 * rows), squeeze=False)
    for ax in axes.flat[len(runs):]:
        ax.set_visible(False)
    for ax, run in zip(axes.flat, runs):
        centres, n = missed_windows(run)
        points = ax.scatter(centres[:, 0], centres[:, 1], c=centres[:, 2], s=6,
                            cmap="viridis", vmin=0.0, vmax=1.0)
        ax.add_patch(plt.Rectangle((EDGE_STRIP, EDGE_STRIP), 1 - 2 * EDGE_STRIP,
                                   1 - 2 * EDGE_STRIP, fill=False, linestyle=":",
                                   color="0.5"))
        ax.set(xlim=(0, 1), ylim=(0, 1), aspect="equal", xlabel="x", ylabel="y",
               title=(f"{run.planner}, rho {run.shape.radio_range:g}\n"
                      f"{n['missed']} of {n['windows']} missed: {n['edge']} at the side,\n"
                      f"{n['low']} below z = {LOW_WINDOW:g}; inside, facing\n"
                      + ", ".join(f"{label} {n[label]}" for label, _, _ in FACINGS)))
        ax.title.set_fontsize(8)
    fig.colorbar(points, ax=axes.ravel().tolist(), label="window height z", shrink=0.8)
    if title:
        fig.suptitle(title, fontsize=9)
    return viz.save_figure(fig, path, tight=False)


def _episode(run, index: int):
    s = run.snapshot
    return (s.height[index], s.target_voxel[index], s.target_valid[index], s.found_at[index],
            run.positions[index], run.active[index])


def episode_picture(path, run, index: int = 0) -> Path:
    """viz.render_episode of one episode of a ShapeRun (world index // trials)."""
    height, voxel, valid, found_at, positions, active = _episode(run, index)
    title = (f"{run.planner}: {run.discovered[index]:.1f}% found "
             f"({run.shape.label()}, world {index // run.trials})")
    return viz.render_episode(path, height, voxel, valid, found_at >= 0, positions, active,
                              run.shape.radio_range, title)


def episode_gif(path, run, index: int = 0, fps: int = 3) -> Path:
    """An animated GIF of one episode: paths growing step by step, windows turning
    green when discovered (matplotlib.animation + PillowWriter)."""
    height, voxel, valid, found_at, positions, active = _episode(run, index)
    size = height.shape[0]
    moving = np.nonzero(active.any(axis=1))[0]
    last = int(moving[-1]) + 1 if len(moving) else 0  # steps until everybody stopped
    fig = plt.figure(figsize=(6, 5.5))
    ax = fig.add_subplot(projection="3d")
    viz.draw_buildings(ax, height, alpha=0.3)
    centres = (voxel[valid] + 0.5) / size
    found_at = found_at[valid]
    missed = ax.scatter(*centres.T, s=5, c="tab:red", depthshade=False)
    found = ax.scatter(*centres[:0].T, s=7, c="tab:green", depthshade=False)
    n = positions.shape[1]
    lines = [ax.plot([], [], [], "-o", markersize=2.5, linewidth=1.5,
                     color=viz.ROBOT_COLOURS[r % len(viz.ROBOT_COLOURS)])[0] for r in range(n)]
    ax.set(xlim=(0, 1), ylim=(0, 1), zlim=(0, 1), xlabel="x", ylabel="y", zlabel="z")

    def frame(k):
        seen = (found_at >= 0) & (found_at <= k)
        found._offsets3d = tuple(centres[seen].T)
        missed._offsets3d = tuple(centres[~seen].T)
        for r, line in enumerate(lines):
            keep = np.concatenate([[True], active[:k, r]])
            p = positions[: k + 1][keep, r]
            line.set_data_3d(p[:, 0], p[:, 1], p[:, 2])
        ax.set_title(f"{run.planner}, step {k}: {100 * seen.sum() / max(len(seen), 1):.1f}% found")
        return [found, missed, *lines]

    anim = animation.FuncAnimation(fig, frame, frames=last + 1, blit=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    anim.save(path, writer=animation.PillowWriter(fps=fps))
    plt.close(fig)
    return path
