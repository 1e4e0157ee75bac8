"""The onboard runtime runs without jax: a drone has NumPy and the standard library.

Two checks. Dynamically: a fresh interpreter whose import system refuses the JAX stack
loads an exported policy and flies a short team episode with `jaxmripp.runtime` alone
(an import anywhere on that path, even a lazy one inside a function, fails the run).
Statically: every import statement under jaxmripp/runtime/ (and the shared contract
jaxmripp/spec/) names NumPy, the standard library, `jaxmripp.spec` or `jaxmripp.runtime`,
including imports inside functions that the episode may not reach.
"""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from jaxmripp import export
from test_runtime import CFG, REPO, init_params

BLOCKED = ("jax", "jaxlib", "flax", "optax", "chex", "distrax", "orbax")


@pytest.fixture(scope="module")
def export_dir(tmp_path_factory):
    """A tiny randomly initialised policy, exported by the JAX side in this process."""
    _, params = init_params(CFG, seed=5)
    out = tmp_path_factory.mktemp("numpy_only_export")
    export.export(CFG, params, out)
    return out


# Runs in the child interpreter. The finder sits first on sys.meta_path, so it sees every
# import before the path finders; raising (not returning None) makes the import fail even
# where a package is installed.
EPISODE = """
import importlib.abc
import sys

BLOCKED = {blocked!r}


class RefuseJax(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{{name}} is not available onboard")
        return None


sys.meta_path.insert(0, RefuseJax())
try:
    import jax  # noqa: F401
except ImportError:
    pass
else:
    raise SystemExit("the import hook let jax through")

import numpy as np

import jaxmripp.runtime as rt
from jaxmripp.runtime import messages

N, ROUNDS = 3, 4
planners = [rt.OnboardPlanner.load({export!r}, robot_id=i, budget=1.0, team_size=N)
            for i in range(N)]
spec = planners[0].spec
g = spec.size
rng = np.random.default_rng(0)
# A synthetic world: a wall of occupied voxels; the "camera" sees a box around the robot
# reaching past the candidate shell (flights need voxels known to be free).
truth = np.zeros((g, g, g), np.int8)
truth[g // 2 + 3, :, : g // 3] = 2
reach = int(np.ceil(spec.shell[1] * g)) + 1


def camera(position):
    centre = np.floor(position * g).astype(int)
    lo, hi = np.maximum(centre - reach, 0), np.minimum(centre + reach + 1, g)
    box = np.stack(np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi)), indexing="ij"),
                   axis=-1).reshape(-1, 3)
    return box, truth[box[:, 0], box[:, 1], box[:, 2]]


position = np.float32([[0.3, 0.3, 0.2], [0.4, 0.3, 0.2], [0.3, 0.4, 0.2]])
heading = [0, 1, 2]
moves = hovers = 0
for t in range(ROUNDS):
    for i, p in enumerate(planners):
        box, codes = camera(position[i])
        if i == 0:  # coordinates as given
            p.sense(position[i], heading[i], box, codes, int(rng.integers(0, 4)))
        else:  # flat indices padded with G^3 ("not observed"), as the JAX camera returns
            flat = np.concatenate([(box[:, 0] * g + box[:, 1]) * g + box[:, 2], [g ** 3] * 5])
            p.sense(position[i], heading[i], flat, np.append(codes, [0] * 5),
                    int(rng.integers(0, 4)))
    def radio(outbox, receive):  # every message reaches the robots in range
        for i, p in enumerate(planners):
            for j, data in enumerate(outbox):
                if j != i and np.linalg.norm(position[i] - position[j]) <= spec.radio_range:
                    assert receive(p, data).sender == j

    radio([p.message() for p in planners], type(planners[0]).receive)
    assert spec.share_maps
    radio([p.map_message() for p in planners], type(planners[0]).receive_map)
    chosen = [p.decide() for p in planners]
    radio([p.intent_message() for p in planners], type(planners[0]).receive_intent)
    decisions = [p.resolve() for p in planners]
    for i, d in enumerate(decisions):
        assert d.mode == "policy" and np.all(np.isfinite(d.pose)), d
        assert np.all((d.position >= 0) & (d.position <= 1))
        assert d.features.shape == (spec.n_candidates, len(rt.FEATURES))
        if d.hover:
            hovers += 1
        else:
            moves += 1
            assert d.safe[d.index] and d.candidates.valid[d.index]
            assert d is chosen[i]
            position[i], heading[i] = d.position, d.heading
greedy = planners[0].decide(mode="greedy")  # the other rule needs nothing more
assert planners[0].resolve() is greedy
assert moves >= N * (ROUNDS - 1), (moves, hovers)
assert all(p.budget_left < 1.0 for p in planners)
assert len(messages.decode(planners[0].message()).poses) >= 2
assert sum(len(h) for h in planners[0].peer_pose.values()) > 0
assert planners[0].last_map_message_bytes > 0 and planners[0].map.top.max() > 0
loaded = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
assert not loaded, loaded
print("FLEW", moves, "moves", hovers, "hovers")
"""


def test_runtime_flies_a_team_episode_with_jax_unimportable(export_dir):
    script = EPISODE.format(blocked=BLOCKED, export=str(export_dir))
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, (result.stdout + result.stderr)[-3000:]
    assert "FLEW" in result.stdout


def _imports(path: Path, package: str) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import statement in the file, at any depth."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if not node.level:
                found.append((node.lineno, node.module))
                continue
            # Relative: resolve against the file's package ("from . import gp" names gp).
            parts = package.split(".")
            base = ".".join(parts[: len(parts) - node.level + 1])
            if node.module:
                found.append((node.lineno, f"{base}.{node.module}"))
            else:
                found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def _allowed(name: str) -> bool:
    top = name.split(".")[0]
    if top == "jaxmripp":
        return name.startswith(("jaxmripp.spec", "jaxmripp.runtime"))
    return top == "numpy" or top == "__future__" or top in sys.stdlib_module_names


@pytest.mark.parametrize("package", ["jaxmripp.runtime", "jaxmripp.spec"])
def test_runtime_and_spec_import_only_numpy_stdlib_and_each_other(package):
    directory = REPO / Path(*package.split("."))
    files = sorted(directory.glob("*.py"))
    assert len(files) >= 3
    bad = [f"{path.relative_to(REPO)}:{line}: {name}" for path in files
           for line, name in _imports(path, package) if not _allowed(name)]
    assert not bad, "imports outside numpy / stdlib / jaxmripp.spec / jaxmripp.runtime:\n" \
        + "\n".join(bad)
    # The spec depends on nothing of the runtime (the runtime builds on it, not vice versa).
    if package == "jaxmripp.spec":
        assert not [n for p in files for _, n in _imports(p, package)
                    if n.startswith("jaxmripp.runtime")]


def test_the_static_check_catches_a_forbidden_import(tmp_path):
    """The checker itself: a lazy jax import inside a function is found."""
    path = tmp_path / "module.py"
    path.write_text("import numpy as np\nfrom . import gp\n\ndef f():\n"
                    "    from jax import numpy as jnp\n    import jaxmripp.sim.env\n")
    names = [name for _, name in _imports(path, "jaxmripp.runtime")]
    assert names == ["numpy", "jaxmripp.runtime.gp", "jax", "jaxmripp.sim.env"]
    assert [_allowed(n) for n in names] == [True, True, False, False]
