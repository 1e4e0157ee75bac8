"""The package's import arrows point one way: spec <- config <- parallel <- sim <- learn <-
evaluation.

Top-level modules (pipeline, export, demo, allocator) and `cli` (the command line, whose
commands call them) sit above every package; the runtime
imports only itself and the spec; `flight` (physics in the loop) flies the runtime in the
simulator's cities, so it may import the runtime and the layers up to sim; `marl` (the
JaxMARL adapter) sits on the layers up to learn, beside evaluation. Nothing imports
`flight` or `marl` but top-level modules and `cli`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import jaxmripp

PACKAGE = Path(jaxmripp.__file__).parent
LAYERS = ("spec", "config", "parallel", "sim", "learn", "evaluation")
TOP_LEVEL = {path.stem for path in PACKAGE.glob("*.py")} - {"__init__", "__main__"}


def imported_subpackages(path: Path) -> set[str]:
    """Second components of every jaxmripp.* name the module imports (lazy ones too)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "jaxmripp":
            parts = node.module.split(".")
            found |= {parts[1]} if len(parts) > 1 else {a.name for a in node.names}
        elif isinstance(node, ast.Import):
            found |= {a.name.split(".")[1] for a in node.names
                      if a.name.startswith("jaxmripp.")}
    return found


def allowed(layer: str) -> set[str]:
    if layer == "cli":
        return {"cli", "runtime", "flight", "marl", *LAYERS, *TOP_LEVEL}
    if layer == "runtime":
        return {"runtime", "spec"}
    if layer == "flight":
        return {"flight", "runtime", *LAYERS[:LAYERS.index("sim") + 1]}
    if layer == "marl":
        return {"marl", *LAYERS[:LAYERS.index("learn") + 1]}
    return set(LAYERS[:LAYERS.index(layer) + 1])


def violations(root: Path) -> list[str]:
    out = []
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root).parts
        if len(parts) < 2:  # top-level modules may import anything
            continue
        for target in imported_subpackages(path) - allowed(parts[0]):
            out.append(f"{path.relative_to(root)} imports jaxmripp.{target}")
    return out


def test_every_import_points_down():
    assert set(LAYERS) | {"runtime", "flight", "marl", "cli"} == {
        p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert violations(PACKAGE) == []


def test_checker_catches_an_upward_import(tmp_path):
    (tmp_path / "sim").mkdir()
    (tmp_path / "sim" / "env.py").write_text(
        "def f():\n    from jaxmripp.evaluation import baselines\n")
    (tmp_path / "runtime").mkdir()
    (tmp_path / "runtime" / "x.py").write_text("from jaxmripp.sim import gp\n")
    (tmp_path / "marl").mkdir()
    (tmp_path / "marl" / "env.py").write_text(
        "from jaxmripp.learn import ppo\nfrom jaxmripp.evaluation import rig\n")
    (tmp_path / "learn").mkdir()
    (tmp_path / "learn" / "x.py").write_text("import jaxmripp.marl.env\n")
    assert violations(tmp_path) == ["learn/x.py imports jaxmripp.marl",
                                    "marl/env.py imports jaxmripp.evaluation",
                                    "runtime/x.py imports jaxmripp.sim",
                                    "sim/env.py imports jaxmripp.evaluation"]
