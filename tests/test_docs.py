"""docs/render.py: the figures and tables of README.md and docs/ are re-rendered from the
result files, and `--check` fails on any that differs."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
render = load_script("docs/render.py")

RESULTS = "docs/results/default/quality.jsonl"


def test_the_documents_agree_with_their_result_files_and_their_links_resolve():
    assert render.differences(ROOT) == []
    assert render.dead_links(ROOT) == []


def test_a_link_to_a_missing_file_or_heading_is_reported(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("# A page\n\n## The `b` part: why\n")
    (tmp_path / "README.md").write_text(
        "[ok](docs/a.md) [ok](docs/a.md#the-b-part-why) [web](https://x.org/none)\n"
        "[gone](docs/none.md)\n[no heading](docs/a.md#nowhere)\n")
    assert render.dead_links(tmp_path) == [
        "README.md:2: no such file: docs/none.md",
        "README.md:3: no such heading: docs/a.md#nowhere"]


@pytest.mark.parametrize("like, value, written", [
    ("55.13", 55.1328, "55.13"), ("55", 55.5001, "56"), ("+0.86", 0.8592, "+0.86"),
    ("+0.86", -0.351, "-0.35"), ("1,234", 6500, "6,500"), ("0.156", 0.15649, "0.156")])
def test_a_figure_keeps_the_format_it_is_written_in(like, value, written):
    assert render.formatted(value, like) == written


def _copy(tmp_path: Path, doc: str) -> Path:
    """A repository of one README and the default world's result file."""
    (tmp_path / "docs" / "results" / "default").mkdir(parents=True)
    shutil.copy(ROOT / RESULTS, tmp_path / RESULTS)
    (tmp_path / "README.md").write_text(doc)
    return tmp_path


def _record(name: str) -> dict:
    lines = (ROOT / RESULTS).read_text().splitlines()
    return next(json.loads(x) for x in lines if json.loads(x)["name"] == name)


def test_a_changed_result_file_or_a_typed_figure_fails_the_check(tmp_path):
    value = _record("quality.policy_pct")["value"]
    doc = f"The policy finds {value:.2f}<!-- fig: {RESULTS} quality.policy_pct --> %.\n"
    root = _copy(tmp_path, doc)
    assert render.differences(root) == []
    # a figure edited by hand
    (root / "README.md").write_text(doc.replace(f"{value:.2f}", f"{value + 1:.2f}"))
    assert [d.split(":")[:2] for d in render.differences(root)] == [["README.md", "1"]]
    # the result file changes under the document; rendering writes the new figure
    (root / "README.md").write_text(doc)
    lines = [json.loads(x) for x in (root / RESULTS).read_text().splitlines()]
    for line in lines:
        if line["name"] == "quality.policy_pct":
            line["value"] = 61.004
    (root / RESULTS).write_text("".join(json.dumps(x) + "\n" for x in lines))
    assert len(render.differences(root)) == 1
    render.differences(root, write=True)
    assert (root / "README.md").read_text().startswith("The policy finds 61.00<!--")
    assert render.differences(root) == []


def test_a_block_is_rendered_from_its_file(tmp_path):
    doc = "<!-- render: include docs/results/default/table.md -->\nold\n<!-- /render -->\n"
    root = _copy(tmp_path, doc)
    table = "| a | b |\n|---|---|\n| 1 | 2 |\n"
    (root / "docs/results/default/table.md").write_text(table)
    assert len(render.differences(root, write=True)) >= 1
    assert (root / "README.md").read_text() == doc.replace("old\n", table)
    assert render.differences(root) == []


@pytest.mark.parametrize("marker, complaint", [
    ("1.0<!-- fig: docs/results/none.jsonl x -->", "no such file"),
    (f"1.0<!-- fig: {RESULTS} quality.no_such -->", "no metric"),
    ("<!-- render: nosuch -->\n<!-- /render -->", "unknown block")])
def test_a_marker_without_a_source_is_an_error_naming_the_line(tmp_path, marker, complaint):
    root = _copy(tmp_path, "title\n\n" + marker + "\n")
    with pytest.raises(render.RenderError, match=f"README.md:3: .*{complaint}"):
        render.differences(root)


def test_the_summary_table_reads_every_planner_and_range():
    summary = json.loads((ROOT / "docs/results/default/summary.json").read_text())["summary"]
    lines = render.summary_table(ROOT, "docs/results/default/summary.json", "policy")
    row = next(r for r in summary if r["planner"] == "policy" and r["radio_range"] == "inf")
    assert lines[2].startswith(f"| policy | {row['mean']:.2f} +- {row['std']:.2f} |")
    assert lines[0].count("rho =") == len({r["radio_range"] for r in summary})


def test_the_seed_line_is_the_mean_and_sample_std_of_the_seeds():
    import statistics

    path = "docs/results/recipe_ahead_seeds/summary.json"
    summary = json.loads((ROOT / path).read_text())["summary"]
    means = [r["mean"] for r in summary if r["radio_range"] == "inf"]
    line = render.seeds_line(ROOT, path, "inf")[0]
    assert line.startswith(f"**{statistics.mean(means):.2f} +- {statistics.stdev(means):.2f}** "
                           f"over {len(means)} training seeds")
    with pytest.raises(render.RenderError, match="0 seeds"):
        render.seeds_line(ROOT, path, "0.3")


def test_the_seed_line_reads_only_the_seeds_of_a_sweep_with_planners(tmp_path):
    rows = [{"planner": name, "radio_range": "inf", "mean": mean}
            for name, mean in (("policy", 90.0), ("nbv_targets", 99.0), ("policy_2", 92.0),
                               ("policy_extra", 10.0), ("policy_3", 94.0))]
    (tmp_path / "summary.json").write_text(json.dumps({"summary": rows}))
    line = render.seeds_line(tmp_path, "summary.json", "inf")[0]
    assert line.startswith("**92.00 +- 2.00** over 3 training seeds at rho = inf "
                           "(policy 90.00, policy_2 92.00, policy_3 94.00;")


ALTERNATIVES = [json.loads(line) for line in
                (ROOT / "docs/results/alternatives.jsonl").read_text().splitlines()
                if line.strip()]


def _figures(source: str) -> str:
    """The text a row's source gives its figures in: a document's (`path` in the tree, or
    `path@commit, section` as it read at that commit), a result file's figures to the two
    decimals the tables show (JSON lines or a JSON document), and for an evaluation
    summary.json also its seeds' mean as docs/render.py's seed line writes it."""
    path, at, rest = source.partition("@")
    if at:
        commit = rest.split(",")[0].strip()
        shown = subprocess.run(["git", "-C", str(ROOT), "show", f"{commit}:{path}"],
                               capture_output=True, text=True)
        assert shown.returncode == 0, (source, shown.stderr)
        return shown.stdout
    file = ROOT / path
    assert file.is_file(), source
    if file.suffix == ".jsonl":
        return " ".join(f"{r['value']:.2f}" for r in render._json_lines(file).values()
                        if isinstance(r.get("value"), (int, float)))
    if file.suffix == ".json":
        def numbers(node):
            if isinstance(node, dict):
                node = list(node.values())
            if isinstance(node, list):
                return [x for item in node for x in numbers(item)]
            is_number = isinstance(node, (int, float)) and not isinstance(node, bool)
            return [f"{node:.2f}"] if is_number else []
        data = json.loads(file.read_text())
        seeds = [render.seeds_line(ROOT, path, rho)[0] for rho in ("inf", "0.1")
                 if isinstance(data, dict) and "summary" in data]
        return " ".join(numbers(data) + seeds)
    return file.read_text()


def _holds(text: str, value: float) -> bool:
    """Whether `text` writes `value` to two decimals as a number of its own."""
    return re.search(rf"(?<![\d.]){value:.2f}(?![\d])", text) is not None


def _at_commit(source: str) -> bool:
    return "@" in source.partition(",")[0]


@pytest.mark.parametrize("which", ["result files", "documents at a commit"])
def test_each_alternative_reads_both_its_figures_from_the_sources_it_names(which):
    """A row of docs/results/alternatives.jsonl gives its % as a figure of `source` and the
    % it is compared with as a figure of `reference_source`: a result file's figure to the
    two decimals the table shows, or the same two decimals in a document's text (at the
    commit the row names, from the repository's history)."""
    wanted = which == "documents at a commit"
    if wanted and subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", "-q",
                                  "f5af2ce^{commit}"], capture_output=True).returncode:
        pytest.skip("the repository's history is not available")
    checked = 0
    for row in ALTERNATIVES:
        for figure, source in ((row["pct"], row["source"]),
                               (row["reference_pct"], row["reference_source"])):
            if _at_commit(source) == wanted:
                assert _holds(_figures(source), figure), (row["setting"], figure, source)
                checked += 1
    assert checked >= (190 if wanted else 50)


def test_a_figure_missing_from_its_source_is_caught():
    """The check above fails for a figure its file does not hold."""
    figures = _figures("docs/results/paper/quality.jsonl")
    best = render.lookup(ROOT, "docs/results/paper/quality.jsonl", "quality.best_baseline_pct")
    assert _holds(figures, best) and not _holds(figures, best + 0.01)
    assert _holds("found 93.57 %", 93.57) and not _holds("found 93.58 %", 93.57)
    assert not _holds("found 193.57 % or 93.575", 93.57)  # a number of its own, whole
    seeds = _figures("docs/results/recipe_belief/summary.json")
    assert _holds(seeds, 54.44) and not _holds(seeds, 54.45)  # the seeds' mean
