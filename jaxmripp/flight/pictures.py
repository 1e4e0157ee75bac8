"""Pictures of a mission: a 3D plot of the paths with the windows found, and a top-down
GIF of the flight as it happened."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxmripp.flight.city import City
from jaxmripp.flight.mission import MissionResult

COLOURS = ("tab:red", "tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink")


def _window_centres(city: City) -> np.ndarray:
    """(T, 3) one point per window: the first of its faces."""
    first = np.unique(city.face_window, return_index=True)[1]
    return city.face_point[first]


def paths_3d(city: City, result: MissionResult, out: Path) -> Path:
    """PNG: buildings, every drone's flown path and the windows found (green) or not."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(8, 7))
    ax = fig.add_subplot(projection="3d")
    lo = city.box_centre - city.box_half
    size = 2 * city.box_half
    ax.bar3d(lo[:, 0], lo[:, 1], lo[:, 2], size[:, 0], size[:, 1], size[:, 2],
             color=(0.75, 0.72, 0.68, 0.25), edgecolor=(0.4, 0.4, 0.4, 0.3), shade=True)
    windows = _window_centres(city)
    ax.scatter(*windows[~result.found].T, s=3, c="0.6", depthshade=False, label="window")
    ax.scatter(*windows[result.found].T, s=6, c="tab:green", depthshade=False,
               label="window found")
    for i in range(result.path.shape[1]):
        colour = COLOURS[i % len(COLOURS)]
        ax.plot(*result.path[:, i].T, color=colour, lw=1.6, label=f"drone {i}")
        ax.scatter(*np.asarray(result.waypoints[i]).T, color=colour, s=10)
    extent = city.frame.extent
    ax.set(xlim=(0, extent[0]), ylim=(0, extent[1]), zlim=(0, extent[2] + 1),
           xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    ax.set_box_aspect((extent[0], extent[1], extent[2] + 1))
    ax.set_title(f"{result.planner}: {result.pct:.1f}% of {result.windows} windows, "
                 f"{len(result.crashes)} crashes, {result.sim_seconds:.0f} s flown")
    ax.legend(loc="upper left", fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def flight_gif(city: City, result: MissionResult, out: Path, frames: int = 60,
               seconds: float = 12.0) -> Path:
    """GIF, top down: buildings shaded by height, windows turning green when first seen,
    the drones and their trails, the simulated time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter
    from matplotlib.patches import Rectangle

    fig, ax = plt.subplots(figsize=(5.2, 5.2))
    extent = city.frame.extent
    top = (city.box_centre + city.box_half)[:, 2]
    for centre, half, h in zip(city.box_centre, city.box_half, top):
        shade = 0.85 - 0.5 * h / extent[2]
        ax.add_patch(Rectangle(centre[:2] - half[:2], *(2 * half[:2]),
                               color=(shade, shade, shade)))
    windows = _window_centres(city)
    dots = ax.scatter(windows[:, 0], windows[:, 1], s=4, c=["0.55"] * len(windows))
    trails = [ax.plot([], [], color=COLOURS[i % len(COLOURS)], lw=1.2)[0]
              for i in range(result.path.shape[1])]
    heads = ax.scatter(result.path[0, :, 0], result.path[0, :, 1], s=30,
                       c=[COLOURS[i % len(COLOURS)] for i in range(result.path.shape[1])],
                       zorder=3)
    title = ax.set_title("")
    ax.set(xlim=(-1, extent[0] + 1), ylim=(-1, extent[1] + 1), aspect="equal",
           xlabel="x (m)", ylabel="y (m)")
    times = np.linspace(0.0, result.path_time[-1], frames)

    def draw(t):
        k = int(np.searchsorted(result.path_time, t, side="right"))
        seen = result.found_time <= t
        dots.set_color(np.where(seen, "tab:green", "0.55"))
        for i, trail in enumerate(trails):
            trail.set_data(result.path[:k, i, 0], result.path[:k, i, 1])
        heads.set_offsets(result.path[max(k - 1, 0), :, :2])
        title.set_text(f"{result.planner}  t = {t:5.0f} s  "
                       f"found {100 * seen.mean():4.1f}%")
        return [dots, heads, title, *trails]

    animation = FuncAnimation(fig, draw, frames=times, blit=False)
    animation.save(out, writer=PillowWriter(fps=max(1, round(frames / seconds))))
    plt.close(fig)
    return out
