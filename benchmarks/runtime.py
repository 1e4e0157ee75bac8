"""Onboard runtime: time from observation to next pose for one robot, NumPy on one core.

A team of N = 3 `OnboardPlanner`s (default config: G = 50, L = 80 candidates, GP capacity
64, policy width 64) flies episodes with budget B = 10 in a synthetic city built here with
NumPy (25 box buildings, 250 facade windows) and a NumPy stand-in for the camera (the
reference's frustum, no occlusion: about 3,000 voxels per view). Per robot and round the
clock covers everything onboard between "the camera delivered" and "the next pose is
known": `sense` (map update, budget, history), building its radio message, decoding and
storing the messages of the robots in range, with `radio.share_maps` the map round (its
map deltas, merging the others'), `decide` (GP updates, candidate sampling, view gain,
safety filter, features, policy forward pass), and the intent round (its intent message,
decoding the others' and `resolve`). Robots start on their take-off pads. The camera
itself is not timed. The policy
has random weights of the default shape (the cost does not depend on their values).

Threads are pinned to one before NumPy loads; jax is never imported (checked at the end).

Usage (from the repository root): python benchmarks/runtime.py [--ahead-branches N]
(N > 0: a policy with the lookahead input of `jaxmripp.spec.layout`, following N candidates)
Prints JSON lines {"name", "value", "unit", ...}; runtime.decision_ms is the headline.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
             "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import figures  # noqa: E402

from jaxmripp.config import Config  # noqa: E402  (pure Python: no jax)
from jaxmripp.config.cli import ArgumentParser  # noqa: E402
from jaxmripp.runtime import ROBOT_STATE, NumpyPolicy, OnboardPlanner  # noqa: E402
from jaxmripp.runtime import weights as fmt  # noqa: E402
from jaxmripp.demo import fly  # noqa: E402  (imports jax only inside main)
from jaxmripp.flight.team import pads  # noqa: E402
from jaxmripp.runtime.mapping import HEADING_VECTORS  # noqa: E402

N, BUDGET, MIN_DECISIONS, WARMUP_EPISODES = 3, 10.0, 600, 1


def emit(name: str, value: float, unit: str, **extra) -> None:
    """One figure as a JSON line, as benchmarks/common.emit prints it, without importing
    jax (the runtime runs on the host CPU)."""
    figures.emit(name, value, unit, device=figures.host_cpu(), **extra)


def random_weights(cfg: Config, n_features: int, rng) -> dict[str, np.ndarray]:
    """Weights of the default policy's shapes (jaxmripp.learn.policy's parameter names)."""
    w, ff = cfg.policy.width, cfg.policy.width * cfg.policy.ff_mult
    shapes = {"embed": (n_features, w), "state_embed": (len(ROBOT_STATE), w),
              "query": (2 * w, w), "pointer_query": (w, w), "pointer_key": (w, w),
              "value_hidden": (w, w), "value_out": (w, 1)}
    blocks = [f"encoder_{i}" for i in range(cfg.policy.layers)] + ["decoder"]
    for block in blocks:
        for name in ("query", "key", "value", "out"):
            shapes[f"{block}/attention/{name}"] = (w, w)
        shapes[f"{block}/ff/hidden"], shapes[f"{block}/ff/out"] = (w, ff), (ff, w)
    weights = {}
    for name, (fan_in, fan_out) in shapes.items():
        weights[f"{name}/kernel"] = rng.normal(0, fan_in ** -0.5, (fan_in, fan_out))
        weights[f"{name}/bias"] = rng.normal(0, 0.1, fan_out)
    norms = [f"{b}/{n}" for b in blocks for n in ("norm_attention", "norm_ff")]
    for norm in norms + ["encoder_norm"]:
        weights[f"{norm}/scale"], weights[f"{norm}/bias"] = np.ones(w), np.zeros(w)
    for gate in ("ir", "iz", "in", "hr", "hz", "hn"):
        weights[f"memory/{gate}/kernel"] = rng.normal(0, w ** -0.5, (w, w))
    for gate in ("ir", "iz", "in", "hn"):
        weights[f"memory/{gate}/bias"] = np.zeros(w)
    return {k: np.asarray(v, np.float32) for k, v in weights.items()}


class City:
    """A NumPy city (height map + facade windows) and a frustum camera without occlusion."""

    def __init__(self, size: int, rng, buildings: int = 25, windows: int = 250, depth: int = 12):
        self.size = size
        self.height = np.zeros((size, size), np.int64)
        lots = np.array([(x, y) for x in range(2, size - 4, 5) for y in range(2, size - 4, 5)])
        for x, y in lots[rng.choice(len(lots), buildings, replace=False)]:
            self.height[x:x + 3, y:y + 3] = rng.integers(int(0.2 * size), int(0.99 * size))
        x, y = np.nonzero(self.height)
        cells = [(a, b, c) for a, b in zip(x, y) for c in range(self.height[a, b])
                 if self.height[a - 1:a + 2, b - 1:b + 2].min() == 0]  # facade columns
        self.windows = np.asarray(cells)[rng.choice(len(cells), windows, replace=False)]
        g = np.arange(-depth, depth + 1)
        a, b, c = (v.ravel() for v in np.meshgrid(g, g, g, indexing="ij"))
        half = np.minimum(depth - 1, (3 * a) // 2 + 1)
        keep = (a >= 0) & (a <= depth - 1) & (np.abs(b) <= half) & (np.abs(c) <= half)
        self.depth, self.frame = depth, np.stack([a[keep], b[keep], c[keep]], -1)

    def cast(self, position, heading):
        """-> flat observed voxels, their codes, windows seen."""
        forward = HEADING_VECTORS[heading].astype(np.int64)
        right = np.array([forward[1], -forward[0], 0])
        voxel = np.clip(np.floor(position * self.size), 0, self.size - 1).astype(np.int64)
        cells = voxel + self.frame[:, :1] * forward + self.frame[:, 1:2] * right \
            + self.frame[:, 2:] * np.array([0, 0, 1])
        cells = cells[np.all((cells >= 0) & (cells < self.size), axis=1)]
        solid = cells[:, 2] < self.height[cells[:, 0], cells[:, 1]]
        flat = (cells[:, 0] * self.size + cells[:, 1]) * self.size + cells[:, 2]
        offset = self.windows - voxel
        f, r, u = offset @ forward, offset @ right, offset[:, 2]
        half = np.minimum(self.depth - 1, (3 * f) // 2 + 1)
        seen = (f >= 0) & (f <= self.depth - 1) & (np.abs(r) <= half) & (np.abs(u) <= half)
        return flat, np.where(solid, 2, 0).astype(np.int8), int(seen.sum())


def episode(spec, policy, seed: int, mode: str):
    """One episode; returns per robot-round seconds and message sizes."""
    rng = np.random.default_rng(seed)
    city = City(spec.size, rng)
    per_robot = BUDGET / N
    steps = max(spec.max_steps, int(np.ceil(per_robot / spec.shell[0])) + 4)
    planners = [OnboardPlanner(spec, i, per_robot, team_size=N, policy=policy, mode=mode,
                               max_steps=steps, seed=seed * 100 + i) for i in range(N)]
    position = pads(spec.start, N, Config().robots.pad_spacing)
    heading = np.full(N, spec.start_heading)
    blocked = np.zeros(N, bool)
    seconds, sizes, map_sizes = [], [], []
    for step in range(steps + 1):
        casts = [city.cast(position[i], heading[i]) for i in range(N)]  # the camera: untimed
        spent = np.zeros(N)
        outbox = []
        for i, planner in enumerate(planners):
            start = time.perf_counter()
            planner.sense(position[i], int(heading[i]), *casts[i], blocked=bool(blocked[i]))
            outbox.append(planner.message())
            spent[i] += time.perf_counter() - start
        sizes += [len(m) for m in outbox]
        gap = np.linalg.norm(position[:, None] - position[None], axis=-1)
        maps = []
        for i, planner in enumerate(planners):
            start = time.perf_counter()
            for j in range(N):
                if j != i and gap[i, j] <= spec.radio_range:
                    planner.receive(outbox[j])
            if spec.share_maps:
                maps.append(planner.map_message())
            spent[i] += time.perf_counter() - start
        map_sizes += [len(m) for m in maps]
        decisions = []
        for i, planner in enumerate(planners):
            start = time.perf_counter()
            for j in range(N):
                if spec.share_maps and j != i and gap[i, j] <= spec.radio_range:
                    planner.receive_map(maps[j])
            planner.decide()
            spent[i] += time.perf_counter() - start
        intents = []
        for i, planner in enumerate(planners):
            start = time.perf_counter()
            intents.append(planner.intent_message())
            spent[i] += time.perf_counter() - start
        for i, planner in enumerate(planners):
            start = time.perf_counter()
            for j in range(N):
                if j != i and gap[i, j] <= spec.radio_range:
                    planner.receive_intent(intents[j])
            decisions.append(planner.resolve())
            spent[i] += time.perf_counter() - start
        if all(d.hover for d in decisions):
            break
        seconds += list(spent)
        for i, d in enumerate(decisions):
            blocked[i] = False
            if not d.hover:
                position[i], blocked[i] = fly(city.height, position[i], d.position, spec.size,
                                              spec.shell[1])
                heading[i] = d.heading
    return seconds, sizes, map_sizes


def main() -> None:
    parser = ArgumentParser(description=__doc__,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ahead-branches", type=int, default=0,
                        help="candidates the lookahead input follows (0: no such input)")
    args = parser.parse_args()
    cfg = Config()  # the defaults: G = 50, K = 20 (L = 80), H = 64, width 64
    cfg = dataclasses.replace(cfg, policy=dataclasses.replace(
        cfg.policy, ahead_branches=args.ahead_branches))
    header = fmt.header(cfg, {"width": cfg.policy.width, "heads": cfg.policy.heads,
                              "layers": cfg.policy.layers, "ff_mult": cfg.policy.ff_mult,
                              "central_critic": False})
    spec = fmt.RuntimeSpec.from_header(json.loads(json.dumps(header)))
    n_features = len(spec.features)
    policy = NumpyPolicy(random_weights(cfg, n_features, np.random.default_rng(0)),
                         header["policy"])
    common = dict(robots=N, size=spec.size, candidates=spec.n_candidates,
                  gp_capacity=spec.gp.capacity, width=cfg.policy.width, threads=1,
                  ahead_branches=spec.ahead_branches)

    for mode in ("policy", "greedy"):
        seconds, sizes, map_sizes, seed = [], [], [], 0
        while len(seconds) < MIN_DECISIONS:
            s, m, maps = episode(spec, policy, seed, mode)
            if seed >= WARMUP_EPISODES:
                seconds += s
                sizes += m
                map_sizes += maps
            seed += 1
        ms = 1e3 * np.asarray(seconds)
        name = "runtime.decision_ms" if mode == "policy" else "runtime.greedy_decision_ms"
        emit(name, statistics.median(ms), "ms", p90=round(float(np.percentile(ms, 90)), 3),
             decisions=len(ms), episodes=seed - WARMUP_EPISODES, **common)
        if mode == "policy":
            emit("runtime.message_bytes", statistics.median(sizes), "bytes")
            if map_sizes:
                emit("runtime.map_message_bytes", statistics.mean(map_sizes), "bytes",
                     median=statistics.median(map_sizes), largest=max(map_sizes))

    # The network alone on one observation, for the ratio.
    rng = np.random.default_rng(1)
    features = rng.normal(size=(spec.n_candidates, n_features)).astype(np.float32)
    mask = rng.random(spec.n_candidates) < 0.8
    state = rng.normal(size=len(ROBOT_STATE)).astype(np.float32)
    memory = policy.initial_memory()
    times = []
    for _ in range(300):
        start = time.perf_counter()
        policy(memory, features, mask, state)
        times.append(time.perf_counter() - start)
    emit("runtime.policy_forward_ms", 1e3 * statistics.median(times[20:]), "ms", **common)
    assert "jax" not in sys.modules, "the runtime benchmark imported jax"


if __name__ == "__main__":
    main()
