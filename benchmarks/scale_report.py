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


def over_best_global(grid: dict, exchange: str, size: int, n: int):
    """(ratio, Welch p) of the policy with `exchange` over the best planner with global
    communication in the cell (size, n), the p from the means and stds; None where either
    figure is missing or rests on fewer than 2 worlds."""
    from scipy import stats  # noqa: PLC0415

    mine = grid.get(("policy", exchange, size, n))
    best = max((v for k, v in grid.items() if k[1:] == ("global", size, n)),
               key=lambda v: v[0], default=None)
    if mine is None or best is None or min(mine[2], best[2]) < 2:
        return None
    return mine[0] / best[0], stats.ttest_ind_from_stats(*mine, *best, equal_var=False).pvalue


def grid_tables(grid: dict, sizes: list[int]) -> str:
    """One markdown table per world size: planner-exchange rows, team-size columns, mean %
    found (std; "-" where a cell has no figure), then the policy with relay over the best
    planner with global communication, with the Welch p of the two; last, one table of
    those ratios (and single hop's) over every world size."""
    rows = pairs_in(grid)

    def ratio_cell(exchange: str, size: int, n: int, with_p: bool) -> str:
        ratio = over_best_global(grid, exchange, size, n)
        if ratio is None:
            return "-"
        return f"{ratio[0]:.3f} (p {ratio[1]:.1g})" if with_p else f"{ratio[0]:.3f}"

    text = []
    for size in sizes:
        teams = sorted({n for _, _, g, n in grid if g == size})
        text += [f"{_world_name(size)}:", "",
                 "| planner, exchange | " + " | ".join(f"N = {n}" for n in teams) + " |",
                 "|---|" + "---|" * len(teams)]
        for planner, exchange in rows:
            cells = [grid.get((planner, exchange, size, n)) for n in teams]
            text.append(f"| {planner}, {exchange.replace('_', ' ')} | " + " | ".join(
                "-" if c is None else f"{c[0]:.2f} ({c[1]:.2f})" for c in cells) + " |")
        text += ["| relay / best global | " + " | ".join(
            ratio_cell("relay", size, n, True) for n in teams) + " |", ""]
    teams = sorted({n for _, _, _, n in grid})
    text += ["The policy over the best planner with global communication:", "",
             "| world, exchange | " + " | ".join(f"N = {n}" for n in teams) + " |",
             "|---|" + "---|" * len(teams)]
    for size in sizes:
        for exchange in ("single_hop", "relay"):
            text.append(f"| {_world_name(size)}, {exchange.replace('_', ' ')} | " + " | ".join(
                ratio_cell(exchange, size, n, False) for n in teams) + " |")
    return "\n".join(text + [""])


def _world_name(size: int) -> str:
    ratio = round((size / config.REFERENCE_SIZE) ** 3)
    return f"{ratio}x world (G = {size}, rho = {PAPER_RADIO[size]})"


def plot_grid(grid: dict, sizes: list[int], path: Path) -> None:
    """% found against team size, one panel per world size, std bands; a colour per
    planner, a line style per exchange."""
    fig, axes = _figure(len(sizes))
    for ax, size in zip(axes, sizes):
        for planner, exchange in pairs_in(grid):
            ns = sorted(n for p, e, g, n in grid if (p, e, g) == (planner, exchange, size))
            _band(ax, ns, [grid[planner, exchange, size, n][0] for n in ns],
                  [grid[planner, exchange, size, n][1] for n in ns], planner, exchange)
        ax.set(title=_world_name(size),
               xlabel="robots N", ylabel="% windows found", ylim=(0, 100))
    _save(fig, axes, path)

