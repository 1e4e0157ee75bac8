"""The scale study's reports: the grid's markdown tables and the figures of benchmarks/scale.py
(% found against the team size per world size, and against the radio range), from
`scale.grid.*` JSON lines collected over runs or from a sweep's runs."""

from __future__ import annotations

import json
from pathlib import Path

from jaxmripp import config

PAPER_RADIO = {75: 0.2, 100: 0.15, 125: 0.12}  # the paper's rho per world size
PLANNERS = ("policy", "coordinated", "nbv", "nbv_team")
# (planner, exchange) pairs in the tables' order: by planner, then by how far news travels
PAIRS = tuple((planner, exchange) for planner in PLANNERS
              for exchange in ("single_hop", "relay", "global"))


def plot_ranges(runs: dict, path: Path, title: str) -> None:
    """% found against the radio range, std bands, one line per planner and short-range
    exchange; the global figures as horizontal bands across the plot."""
    fig, ax = _figure(1, width=5.6)
    ranges = sorted({key[3] for key in runs if key[1] != "global"})
    for planner, exchange in PAIRS:
        found = {key[3]: run.discovered for key, run in runs.items()
                 if key[:2] == (planner, exchange)}
        if not found:
            continue
        if exchange == "global":  # one figure (at rho = inf), drawn across the ranges
            xs, each = ranges, [found[float("inf")]] * len(ranges)
        else:
            xs = sorted(found)
            each = [found[x] for x in xs]
        _band(ax[0], xs, [f.mean() for f in each],
              [f.std(ddof=1) if len(f) > 1 else 0.0 for f in each], planner, exchange,
              marker=None if exchange == "global" else "o")
    ax[0].set(title=title, xlabel="radio range rho (fraction of the world)",
              ylabel="% windows found")
    _save(fig, ax, path)


def _figure(panels: int, width: float = 4.2):
    """A row of `panels` axes, `width` inches each."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, axes = plt.subplots(1, panels, figsize=(width * panels, 3.6),
                             squeeze=False)
    return fig, axes[0]


def _band(ax, xs, mean, std, planner: str, exchange: str, marker="o") -> None:
    """One planner-exchange line with its mean +- std band: a colour per planner, a line
    style per exchange."""
    colour = f"C{PLANNERS.index(planner)}"
    style = {"single_hop": ":", "relay": "--", "global": "-"}[exchange]
    ax.plot(xs, mean, marker=marker, color=colour, linestyle=style,
            label=f"{planner}, {exchange.replace('_', ' ')}")
    ax.fill_between(xs, [m - s for m, s in zip(mean, std)], [m + s for m, s in zip(mean, std)],
                    color=colour, alpha=0.12)


def _save(fig, axes, path: Path) -> None:
    from jaxmripp.evaluation import viz  # noqa: PLC0415

    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right", handlelength=3.5)
    viz.save_figure(fig, path)


def read_grid(path: Path) -> dict:
    """{(planner, exchange, G, N): (mean, std, worlds)} from the scale.grid.* lines of a
    JSON-lines file (other lines are skipped; a cell given twice keeps its last line; a line
    without a world count counts as 1)."""
    grid = {}
    for line in path.read_text().splitlines():
        record = json.loads(line) if line.startswith("{") else {}
        parts = record.get("name", "").split(".")
        if len(parts) == 6 and parts[:2] == ["scale", "grid"]:
            planner, exchange, size, n = parts[2], parts[3], int(parts[4][1:]), int(parts[5][1:])
            grid[planner, exchange, size, n] = (record["value"], record["std"],
                                                record.get("worlds", 1))
    return grid


def pairs_in(grid: dict) -> list[tuple[str, str]]:
    """The (planner, exchange) pairs with a figure in some cell of the grid, in PAIRS order."""
    return [pair for pair in PAIRS if any(key[:2] == pair for key in grid)]


def grid_tables(grid: dict, sizes: list[int]) -> str:
    """One markdown table per world size: planner-exchange rows, team-size columns, mean %
    found (std; "-" where a cell has no figure), then the policy with relay over the best
    planner with global communication, with the Welch p of the two (from means and stds)."""
    from scipy import stats  # noqa: PLC0415

    rows = pairs_in(grid)

    def relay_vs_best_global(size: int, n: int) -> str:
        relay = grid.get(("policy", "relay", size, n))
        best = max((v for k, v in grid.items() if k[1:] == ("global", size, n)),
                   key=lambda v: v[0], default=None)
        if relay is None or best is None or min(relay[2], best[2]) < 2:
            return "-"
        p = stats.ttest_ind_from_stats(*relay, *best, equal_var=False).pvalue
        return f"{relay[0] / best[0]:.3f} (p {p:.1g})"

    text = []
    for size in sizes:
        teams = sorted({n for _, _, g, n in grid if g == size})
        ratio = round((size / config.REFERENCE_SIZE) ** 3)
        text += [f"{ratio}x world (G = {size}, rho = {PAPER_RADIO[size]}):", "",
                 "| planner, exchange | " + " | ".join(f"N = {n}" for n in teams) + " |",
                 "|---|" + "---|" * len(teams)]
        for planner, exchange in rows:
            cells = [grid.get((planner, exchange, size, n)) for n in teams]
            text.append(f"| {planner}, {exchange.replace('_', ' ')} | " + " | ".join(
                "-" if c is None else f"{c[0]:.2f} ({c[1]:.2f})" for c in cells) + " |")
        text += ["| relay / best global | " + " | ".join(
            relay_vs_best_global(size, n) for n in teams) + " |", ""]
    return "\n".join(text)


def plot_grid(grid: dict, sizes: list[int], path: Path) -> None:
    """% found against team size, one panel per world size, std bands; a colour per
    planner, a line style per exchange."""
    fig, axes = _figure(len(sizes))
    for ax, size in zip(axes, sizes):
        for planner, exchange in pairs_in(grid):
            ns = sorted(n for p, e, g, n in grid if (p, e, g) == (planner, exchange, size))
            _band(ax, ns, [grid[planner, exchange, size, n][0] for n in ns],
                  [grid[planner, exchange, size, n][1] for n in ns], planner, exchange)
        ratio = round((size / config.REFERENCE_SIZE) ** 3)
        ax.set(title=f"{ratio}x world (G = {size}, rho = {PAPER_RADIO[size]})",
               xlabel="robots N", ylabel="% windows found", ylim=(0, 100))
    _save(fig, axes, path)

