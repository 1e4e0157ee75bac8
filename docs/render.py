"""Render the figures and tables of README.md and docs/*.md from the result files.

    python docs/render.py            rewrite every generated part in place
    python docs/render.py --check    change nothing; exit 1 listing each part that differs

Two kinds of generated part, both invisible on a rendered page:

* a figure in prose: the number followed by a marker naming its source,
  `55.13<!-- fig: docs/results/default/quality.jsonl quality.policy_pct -->`. The source is a
  JSON-lines result file (the line whose "name" is the metric; `name:field` reads another
  field of that line) or a policy's metadata.json (a top-level key, else the first
  evaluation's figure of that name). The written number sets the format: its decimals, a
  leading "+", thousands commas.
* a block between `<!-- render: KIND ARGS -->` and `<!-- /render -->`, whose lines are
  the output of one of the renderers in `BLOCKS` (tables from evaluation summaries, the
  shipped policies' metadata, the generalisation cells, the alternatives measured).

Paths are relative to the repository root. A missing file, metric or block kind is an
error naming the document and line.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIGURE = re.compile(r"(?P<number>[+-]?\d[\d,]*(?:\.\d+)?)(?P<marker><!-- fig: (?P<path>\S+) "
                    r"(?P<key>\S+) -->)")
BLOCK = re.compile(r"(?P<open><!-- render: (?P<spec>[^>]*?) -->\n)(?P<body>.*?)"
                   r"(?P<close><!-- /render -->)", re.S)


class RenderError(Exception):
    """A marker whose source or kind does not exist."""


# ----- sources -------------------------------------------------------------------------------

def _json_lines(path: Path) -> dict[str, dict]:
    lines = {}
    for line in path.read_text().splitlines():
        if line.strip():
            record = json.loads(line)
            lines[record["name"]] = record
    return lines


def lookup(root: Path, path: str, key: str):
    """The value `key` names in the result file at `path` (see the module docstring)."""
    file = root / path
    if not file.is_file():
        raise RenderError(f"{path}: no such file")
    if file.suffix == ".jsonl":
        name, _, field = key.partition(":")
        record = _json_lines(file).get(name)
        if record is None or (field or "value") not in record:
            raise RenderError(f"{path}: no metric {key}")
        return record[field or "value"]
    data = json.loads(file.read_text())
    if key in data:
        return data[key]
    for evaluation in data.get("evaluations", []):
        if key in evaluation.get("figures", {}):
            return evaluation["figures"][key]
    raise RenderError(f"{path}: no figure {key}")


def formatted(value: float, like: str) -> str:
    """`value` written as `like` is: the same decimals, sign and thousands separator."""
    decimals = len(like.split(".")[1]) if "." in like else 0
    text = f"{float(value):,.{decimals}f}" if "," in like else f"{float(value):.{decimals}f}"
    return "+" + text if like.startswith("+") and float(value) >= 0 else text


# ----- blocks --------------------------------------------------------------------------------

def _pct(row: dict) -> str:
    return "-" if math.isnan(float(row["mean"])) else f"{row['mean']:.2f} +- {row['std']:.2f}"


def _rho(value) -> str:
    return "inf" if str(value) == "inf" else f"{float(value):g}"


def summary_table(root: Path, path: str, *planners: str) -> list[str]:
    """Mean +- std of % found per planner (rows) and radio range (columns) of an evaluation
    summary.json, in the file's order or the order given."""
    rows = json.loads((root / path).read_text())["summary"]
    ranges = list(dict.fromkeys(_rho(r["radio_range"]) for r in rows))
    order = list(planners) or list(dict.fromkeys(r["planner"] for r in rows))
    cells = {(r["planner"], _rho(r["radio_range"])): r for r in rows}
    missing = [p for p in order if not any((p, rho) in cells for rho in ranges)]
    if missing:
        raise RenderError(f"{path}: no planner {', '.join(missing)}")
    runs = {r["runs"] for r in rows}
    lines = ["| planner | " + " | ".join(f"% found, rho = {rho}" for rho in ranges) + " |",
             "|---" * (len(ranges) + 1) + "|"]
    lines += [f"| {p} | " + " | ".join(_pct(cells[p, rho]) if (p, rho) in cells else "-"
                                       for rho in ranges) + " |" for p in order]
    return lines + ["", f"Mean +- std over {'/'.join(map(str, sorted(runs)))} episodes "
                        f"({path})."]


# A shipped policy's headline figure: the Table I protocol at rho = inf, else the large-team
# world with relay.
HEADLINES = ("quality.policy_pct", "scale.pct.policy.relay")


_SEED_NAME = re.compile(r"policy(_\d+)?")


def seeds_line(root: Path, path: str, rho: str = "inf") -> list[str]:
    """The mean +- standard deviation (ddof 1) over training seeds of an evaluation
    summary.json at radio range `rho`: its policies (`policy`, `policy_2`, ... as
    benchmarks/quality.py --seeds names one recipe's seeds) when the sweep also ran
    planners, else every planner of it (sweeps of seeds alone may name them s0, s1, ...)."""
    rows = [r for r in json.loads((root / path).read_text())["summary"]
            if _rho(r["radio_range"]) == rho]
    if any(_SEED_NAME.fullmatch(r["planner"]) for r in rows):
        rows = [r for r in rows if _SEED_NAME.fullmatch(r["planner"])]
    if len(rows) < 2:
        raise RenderError(f"{path}: {len(rows)} seeds at rho = {rho}; allowed: 2 or more")
    means = [float(r["mean"]) for r in rows]
    mean = sum(means) / len(means)
    std = math.sqrt(sum((m - mean) ** 2 for m in means) / (len(means) - 1))
    each = ", ".join(f"{r['planner']} {float(r['mean']):.2f}" for r in rows)
    return [f"**{mean:.2f} +- {std:.2f}** over {len(rows)} training seeds at rho = {rho} "
            f"({each}; {path})."]


def policies_table(root: Path) -> list[str]:
    """The shipped policies: how each was trained and its headline figure."""
    lines = ["| policy | trained by | seed | minutes (2 cores) | updates | % found | figure | "
             "results |", "|---|---|---|---|---|---|---|---|"]
    for meta in sorted((root / "pretrained").glob("*/metadata.json")):
        data = json.loads(meta.read_text())
        evaluation = (data.get("evaluations") or [{}])[0]
        figures = evaluation.get("figures", {})
        metric = next((m for m in HEADLINES if m in figures), None)
        minutes = data.get("train_minutes")
        # an override names the seed; a preset keeps train.seed's default, 0
        seed = re.search(r"train\.seed=(\d+)", data["command"])
        lines.append(f"| `{meta.parent.name}` | `{data['command']}` | "
                     f"{seed[1] if seed else '-' if data['command'].endswith('.yaml') else 0} | "
                     f"{'-' if minutes is None else f'{minutes:.1f}'} | {data['updates']} | "
                     f"{'-' if metric is None else f'{figures[metric]:.2f}'} | "
                     f"{metric or '-'} | "
                     f"{evaluation.get('results', '-')} |")
    return lines


def generalize_table(root: Path, path: str) -> list[str]:
    """One row per cell of benchmarks/generalize.py's output, with the upper references'
    columns where it ran them (--ceilings)."""
    records = _json_lines(root / path)
    cells = {name.removeprefix("generalize.cell."): r for name, r in records.items()
             if name.startswith("generalize.cell.")}
    ceilings = [c for c in ("rate_ceiling", "city_ceiling")
                if all(f"{c}_pct" in r for r in cells.values())]
    heads = {"rate_ceiling": "oracle_rate %", "city_ceiling": "oracle_city %"}
    lines = ["| cell | policy % | best classical | its % | ratio | paired p |"
             + "".join(f" {heads[c]} |" for c in ceilings),
             "|---|---|---|---|---|---|" + "---|" * len(ceilings)]
    for name, r in cells.items():
        lines.append(f"| {name} | {r['policy_pct']:.2f} | {r['best']} | {r['best_pct']:.2f} | "
                     f"{r['value']:.3f} | {r['p']:.3f} |"
                     + "".join(f" {r[f'{c}_pct']:.2f} |" for c in ceilings))
    if "generalize.cells_won" not in records:  # a run stopped before its summary lines
        return lines + ["", f"Cells run: {len(cells)} ({path})."]
    won, geomean = records["generalize.cells_won"], records["generalize.geomean_ratio"]
    above = "".join(f", {heads[c].removesuffix(' %')} / best classical "
                    f"{records[f'generalize.geomean_{c}_ratio']['value']:.3f}" for c in ceilings)
    return lines + ["", f"Cells won {int(won['value'])} of {len(cells)}, geometric mean ratio "
                        f"{geomean['value']:.3f}{above} ({path})."]


def alternatives_table(root: Path, path: str) -> list[str]:
    """The settings measured and not adopted, one row each."""
    lines = ["| area | setting | % found | against | its % | protocol | source |",
             "|---|---|---|---|---|---|---|"]
    for line in (root / path).read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            ref = r.get("reference_pct")
            lines.append(f"| {r['area']} | {r['setting']} | {r['pct']:.2f} | {r['reference']} | "
                         f"{'-' if ref is None else f'{ref:.2f}'} | {r['protocol']} | "
                         f"{r['source']} |")
    return lines


def _number(value) -> str:
    if isinstance(value, int) or float(value).is_integer():
        return f"{int(value):,}"
    # four significant digits: a ratio such as 1.046 must not read as its target 1.05
    return f"{value:,.4g}" if abs(value) < 10 else f"{value:,.1f}"


def benchmarks_table(root: Path, path: str) -> list[str]:
    """The speed, safety and flight figures of the benchmark scripts, one per row."""
    lines = ["| figure | what | value | machine | target | command |",
             "|---|---|---|---|---|---|"]
    for name, r in _json_lines(root / path).items():
        lines.append(f"| `{name}` | {r['what']} | {_number(r['value'])} {r['unit']} | "
                     f"{r['device']} | {r['target']} | `{r['command']}` |")
    return lines


def metrics_table(root: Path, path: str, prefix: str) -> list[str]:
    """Every metric of a JSON-lines result file whose name starts with `prefix`."""
    lines = ["| metric | value | unit | std | worlds |", "|---|---|---|---|---|"]
    for name, r in _json_lines(root / path).items():
        if name.startswith(prefix):
            lines.append(f"| {name.removeprefix(prefix)} | {r['value']:.2f} | "
                         f"{r.get('unit', '')} | {r.get('std', '-')} | {r.get('worlds', '-')} |")
    if len(lines) == 2:
        raise RenderError(f"{path}: no metric starts with {prefix}")
    return lines + ["", f"({path})"]


def scale_grid(root: Path, path: str) -> list[str]:
    """benchmarks/scale.py --grid's output (`scale.grid.PLANNER.EXCHANGE.gG.nN`, % found)
    as one row per planner and exchange, one column per world size and team size."""
    cells, columns = {}, {}
    for name, r in _json_lines(root / path).items():
        planner, exchange, size, team = name.removeprefix("scale.grid.").split(".")
        cells[(planner, exchange), (size, team)] = r["value"]
        columns[int(size[1:]), int(team[1:])] = (size, team)
    order = [columns[k] for k in sorted(columns)]
    rows = list(dict.fromkeys(row for row, _ in cells))
    lines = ["| planner | radio | " + " | ".join(f"G = {g[1:]}, N = {n[1:]}" for g, n in order)
             + " |", "|---|---" + "|---" * len(order) + "|"]
    lines += [f"| {p} | {x} | " + " | ".join(f"{cells[(p, x), c]:.2f}" if ((p, x), c) in cells
                                             else "-" for c in order) + " |" for p, x in rows]
    return lines + ["", f"% found, mean over the worlds of each cell ({path})."]


def markdown_table(root: Path, path: str, number: str) -> list[str]:
    """The `number`-th (from 1) table of a results.md an evaluation wrote, with the heading
    above it."""
    text = (root / path).read_text().split("\n\n")
    tables = [i for i, part in enumerate(text) if part.startswith("|")]
    if not 1 <= int(number) <= len(tables):
        raise RenderError(f"{path}: has {len(tables)} tables, not {number}")
    i = tables[int(number) - 1]
    heading = [text[i - 1], ""] if i and text[i - 1].startswith("#") else []
    return [*heading, *text[i].splitlines(), "", f"({path})"]


def include(root: Path, path: str) -> list[str]:
    """A file that a command wrote, as it is."""
    return (root / path).read_text().rstrip("\n").splitlines()


BLOCKS = {"summary": summary_table, "policies": policies_table,
          "generalize": generalize_table, "alternatives": alternatives_table,
          "metrics": metrics_table, "seeds": seeds_line, "benchmarks": benchmarks_table,
          "scale_grid": scale_grid, "table": markdown_table, "include": include}


# ----- documents -----------------------------------------------------------------------------

def render_text(text: str, root: Path, where: str = "") -> str:
    """`text` with every figure and block re-rendered from the files under `root`."""
    def line_of(match) -> str:
        return f"{where}:{text.count(chr(10), 0, match.start()) + 1}"

    def block(match) -> str:
        kind, *args = match["spec"].split()
        if kind not in BLOCKS:
            raise RenderError(f"{line_of(match)}: unknown block {kind!r}; allowed: "
                              f"{', '.join(BLOCKS)}")
        try:
            body = BLOCKS[kind](root, *args)
        except (OSError, KeyError, TypeError, ValueError, RenderError) as error:
            raise RenderError(f"{line_of(match)}: {kind}: {error}") from error
        return match["open"] + "\n".join(body) + "\n" + match["close"]

    def figure(match) -> str:
        try:
            value = lookup(root, match["path"], match["key"])
        except RenderError as error:
            raise RenderError(f"{line_of(match)}: {error}") from error
        return formatted(value, match["number"]) + match["marker"]

    return FIGURE.sub(figure, BLOCK.sub(block, text))


def documents(root: Path) -> list[Path]:
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def differences(root: Path = ROOT, write: bool = False) -> list[str]:
    """`doc:line` of each generated part that differs from its files (rewritten if
    `write`)."""
    found = []
    for doc in documents(root):
        text = doc.read_text()
        rendered = render_text(text, root, str(doc.relative_to(root)))
        if rendered != text:
            old, new = text.splitlines(), rendered.splitlines()
            found += [f"{doc.relative_to(root)}:{i + 1}: {a.strip()[:60]!r} -> "
                      f"{b.strip()[:60]!r}" for i, (a, b) in enumerate(zip(old, new)) if a != b]
            if len(old) != len(new):
                found.append(f"{doc.relative_to(root)}: a generated block changes length")
            if write:
                doc.write_text(rendered)
    return found


LINK = re.compile(r"\]\((?!https?://|mailto:)(?P<target>[^)#\s]*)(?:#(?P<anchor>[^)\s]*))?\)")


def _anchors(doc: Path) -> set[str]:
    """GitHub's anchors of a markdown file's headings."""
    text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
    headings = re.findall(r"^#+ (.*)$", text, flags=re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings}


def dead_links(root: Path = ROOT) -> list[str]:
    """`doc:line: target` of each relative link whose file or heading does not exist."""
    found = []
    for doc in documents(root):
        text = doc.read_text()
        for match in LINK.finditer(text):
            target = doc.parent / match["target"] if match["target"] else doc
            anchor = match["anchor"]
            if not target.exists() or (anchor and target.suffix == ".md"
                                       and anchor not in _anchors(target)):
                line = text.count("\n", 0, match.start()) + 1
                found.append(f"{doc.relative_to(root)}:{line}: no such "
                             f"{'heading' if target.exists() else 'file'}: {match[0][2:-1]}")
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="change nothing; exit 1 if any generated part differs")
    args = parser.parse_args(argv)
    try:
        changed = differences(write=not args.check)
        found = (changed if args.check else []) + dead_links()
    except RenderError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    if found:
        print("\n".join(found))
        print(f"error: {len(found)} generated lines differ from the result files or links "
              "lead nowhere; `make docs` re-renders the figures", file=sys.stderr)
        return 1
    print(f"{'checked' if args.check else 'rendered'}: "
          f"{', '.join(str(d.relative_to(ROOT)) for d in documents(ROOT))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
