"""docs/render.py: the figures and tables of README.md and docs/ are re-rendered from the
result files, and `--check` fails on any that differs."""

from __future__ import annotations

import json
import shutil
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


def test_each_alternative_reads_its_figures_from_the_result_file_it_names():
    """A row of docs/results/alternatives.jsonl whose source is a result file of figures
    gives its % as one of that file's figures, to the two decimals the table shows."""
    rows = [json.loads(line) for line in
            (ROOT / "docs/results/alternatives.jsonl").read_text().splitlines() if line.strip()]
    checked = 0
    for row in rows:
        source = ROOT / row["source"]
        if source.suffix != ".jsonl":  # a document at a commit: its figure is in its prose
            continue
        assert source.is_file(), row["source"]
        figures = {round(r["value"], 2) for r in render._json_lines(source).values()
                   if isinstance(r.get("value"), (int, float))}
        assert round(row["pct"], 2) in figures, (row["setting"], row["pct"], row["source"])
        checked += 1
    assert checked >= 19
