"""The exporter (`jaxmripp.export`): its layout check and its command line."""

from __future__ import annotations

import copy
import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from jaxmripp import config as cfgmod, export
from jaxmripp.config import presets
from jaxmripp.learn import policy as policymod
from jaxmripp.learn.checkpoint import Checkpoints
from jaxmripp.learn.train import Trainer
from jaxmripp.runtime import weights
from test_runtime import CFG, REPO, init_params


@pytest.fixture(scope="module")
def flat_params():
    _, params = init_params(CFG, seed=1)
    return params, policymod.flatten_params(params)


# ---------------------------------------------------------------------------------------
# The layout check


def test_a_matching_export_passes_the_check(flat_params):
    _, flat = flat_params
    export.check_layout(export.header(CFG), flat)  # no error


@pytest.mark.parametrize("doctor", [
    lambda h: h["layout"]["features"].reverse(),
    lambda h: h["layout"]["features"].pop(),
    lambda h: h["layout"]["features"].append("altitude"),
    lambda h: h["layout"]["robot_state"].remove("step"),
    lambda h: h.pop("layout"),
], ids=["reordered", "column dropped", "column added", "state column dropped", "no layout"])
def test_a_doctored_header_layout_is_refused(flat_params, doctor):
    _, flat = flat_params
    head = copy.deepcopy(export.header(CFG))
    doctor(head)
    with pytest.raises(export.ExportError, match="layout") as err:
        export.check_layout(head, flat)
    assert "\n" not in str(err.value)


def test_weights_of_another_input_width_are_refused(flat_params):
    _, flat = flat_params
    head = export.header(CFG)
    narrow = dict(flat, **{"embed/kernel": flat["embed/kernel"][:-1]})
    with pytest.raises(export.ExportError, match="embed reads 20 inputs; .* gives 21"):
        export.check_layout(head, narrow)
    wide = dict(flat, **{"state_embed/kernel": np.zeros((10, CFG.policy.width), np.float32)})
    with pytest.raises(export.ExportError, match="state_embed reads 10 inputs"):
        export.check_layout(head, wide)
    # A central critic reads every robot's state plus the team values.
    central = copy.deepcopy(head)
    central["policy"]["central_critic"] = True
    with pytest.raises(export.ExportError, match="no layer global_embed; .* reading 29 inputs"):
        export.check_layout(central, flat)
    width = CFG.robots.count * len(weights.ROBOT_STATE) + 2
    export.check_layout(central, dict(flat, **{
        "global_embed/kernel": np.zeros((width, CFG.policy.width), np.float32)}))


AHEAD = cfgmod.load(REPO / "tests/smoke.yaml", ["world.size=30", "robots.count=3",
                                                   "policy.ahead_branches=4",
                                                   "policy.ahead_discount=1.5"])


def test_a_policy_with_the_lookahead_input_exports_and_decides_onboard(flat_params, tmp_path):
    """An export with the lookahead input (policy.ahead_branches) carries its settings and
    one more column; the runtime builds that column from its generator's draws after the
    candidates' and feeds all of them to the policy. Weights of the plain width are refused
    under its header."""
    from jaxmripp.runtime import OnboardPlanner, lookahead
    from jaxmripp.runtime import candidates as np_candidates
    from jaxmripp.spec import layout

    _, flat = flat_params  # 21 inputs: not what an AHEAD header promises
    with pytest.raises(export.ExportError, match="embed reads 21 inputs; .* gives 22"):
        export.check_layout(export.header(AHEAD), flat)
    _, params = init_params(AHEAD, seed=5)
    export.export(AHEAD, params, tmp_path)
    exported = weights.load(tmp_path)
    spec = exported.spec
    assert (spec.ahead_branches, spec.ahead_discount) == (4, 1.5)
    assert spec.features == layout.FEATURES + ("ahead_rate",) and exported.policy.n_features == 22
    older = weights.load(REPO / "pretrained/default_fast").spec  # exported before
    assert older.ahead_branches == 0 and older.gain[2:] == (True, "nearby")  # these fields

    planner = OnboardPlanner(spec, 0, 2.0, policy=exported.policy, seed=7)
    g = spec.size  # a ball of known free space around the robot, unknown beyond
    centres = (np.stack(np.unravel_index(np.arange(g ** 3), (g, g, g)), -1) + 0.5) / g
    near = np.flatnonzero(np.linalg.norm(centres - 0.5, axis=-1) < 0.35)
    planner.sense(np.full(3, 0.5, np.float32), 1, near, np.zeros(near.size, np.int8), 0)
    budget_left = planner.budget_left
    d = planner.decide()
    twin = np.random.default_rng(7)
    draws = twin.random((spec.positions * spec.oversample - 1, 3), np.float32)
    c = np_candidates.sample(draws, planner.position, planner.heading, budget_left,
                             planner.map, np.zeros((0, 3), np.float32), spec)
    np.testing.assert_array_equal(c.position, d.candidates.position)
    rates = lookahead.ahead_rates(twin.random(lookahead.draw_shape(spec), np.float32),
                                  d.features[:, :-1], c.valid, c, budget_left, planner.map,
                                  np.zeros((0, 3), np.float32), spec)
    np.testing.assert_array_equal(d.features[:, -1], rates)
    one_step = layout.view_value(d.features[:, layout.FEATURES.index("view_unknown_per_cost")],
                                 d.features[:, layout.FEATURES.index("view_facade_per_cost")],
                                 np.float32(spec.ahead_facade_weight))
    assert np.sum(rates[c.valid] > one_step[c.valid] * 1.001) >= 1  # some look ahead
    _, logits, _ = exported.policy(exported.policy.initial_memory(), d.features, d.mask,
                                   d.robot_state)
    np.testing.assert_array_equal(d.scores, logits)
    # The other modes neither read the input nor spend draws on it.
    greedy = OnboardPlanner(spec, 0, 2.0, mode="greedy", seed=7)
    greedy.sense(np.full(3, 0.5, np.float32), 1, near, np.zeros(near.size, np.int8), 0)
    g = greedy.decide()
    assert g.features.shape[1] == len(layout.FEATURES)
    np.testing.assert_array_equal(g.candidates.position, c.position)
    fresh = np.random.default_rng(7)
    fresh.random(draws.shape, np.float32)  # the candidates' draws, and nothing more
    np.testing.assert_array_equal(greedy.rng.random(3), fresh.random(3))


RATED = cfgmod.load(REPO / "tests/smoke.yaml", [
    "world.size=30", "robots.count=3", "policy.ahead_branches=4", "policy.ahead_discount=1.5",
    "policy.belief_features=true", "policy.ahead_rated=true"])


def test_a_rated_lookahead_input_weighs_the_facade_by_the_robots_belief(tmp_path):
    """Exported with policy.ahead_rated, the header says so and the onboard planner builds
    the lookahead column from its own belief's facade rates: a building whose windows it
    found rates above the prior, so the column differs from the unrated value."""
    from jaxmripp.runtime import OnboardPlanner, belief, lookahead
    from jaxmripp.runtime.mapping import FREE, OCCUPIED
    from jaxmripp.spec import layout

    _, params = init_params(RATED, seed=5)
    export.export(RATED, params, tmp_path)
    exported = weights.load(tmp_path)
    spec = exported.spec
    assert spec.ahead_rated and spec.features[-3:] == ("view_windows", "view_windows_per_cost",
                                                       "ahead_rate")
    g = spec.size
    xyz = np.stack(np.unravel_index(np.arange(g ** 3), (g, g, g)), -1)
    wall = np.flatnonzero((xyz[:, 0] == 20) & (xyz[:, 1] >= 12) & (xyz[:, 1] < 18) &
                          (xyz[:, 2] < 22))  # its far side and ends unknown
    air = np.flatnonzero((np.linalg.norm((xyz + 0.5) / g - 0.5, axis=-1) < 0.3) &
                         (xyz[:, 0] < 20))
    planner = OnboardPlanner(spec, 0, 2.0, policy=exported.policy, seed=7)
    planner.sense(np.full(3, 0.5, np.float32), 0, np.r_[air, wall],
                  np.r_[np.full(air.size, FREE), np.full(wall.size, OCCUPIED)].astype(np.int8),
                  4, windows=wall[::5])
    budget_left = planner.budget_left
    twin = np.random.default_rng(7)
    twin.random((spec.positions * spec.oversample - 1, 3), np.float32)  # the candidates'
    d = planner.decide()
    uniforms = twin.random(lookahead.draw_shape(spec), np.float32)
    rates = belief.facade_rates(planner.map, spec.belief_strength, spec.belief_prior,
                                spec.gain_facade)
    assert rates.max() > belief.spec.quantised(np.float32(1.0))  # found windows: above prior
    facade = layout.FEATURES.index("view_facade")
    assert np.any(d.features[d.mask, facade] > 0)  # candidates see the wall's far side
    args = (uniforms, d.features[:, :-1], d.mask, d.candidates, budget_left, planner.map,
            np.zeros((0, 3), np.float32))
    np.testing.assert_array_equal(d.features[:, -1], lookahead.ahead_rates(*args, spec, rates))
    unrated = lookahead.ahead_rates(*args, dataclasses.replace(spec, ahead_rated=False))
    assert np.any(np.abs(d.features[:, -1] - unrated) > 1e-3 * np.abs(unrated).max())
    with pytest.raises(ValueError, match="facade rates"):
        lookahead.ahead_rates(*args, spec)


def test_export_refuses_a_doctored_header_and_writes_nothing(flat_params, tmp_path,
                                                             monkeypatch):
    params, _ = flat_params
    good = export.header(CFG)
    doctored = copy.deepcopy(good)
    doctored["layout"]["features"][0], doctored["layout"]["features"][1] = "dy", "dx"
    monkeypatch.setattr(export, "header", lambda cfg, source=None: doctored)
    with pytest.raises(export.ExportError, match="layout.features"):
        export.export(CFG, params, tmp_path / "out")
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------------------
# The command line: python -m jaxmripp.export RUN_DIR [--best] [--out DIR]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A training run directory as `jaxmripp.learn.train.train` leaves it, without the
    training: config.yaml and one checkpoint of the initial state."""
    cfg = cfgmod.load(REPO / "tests/smoke.yaml")
    run = tmp_path_factory.mktemp("runs") / "tiny"
    run.mkdir()
    (run / "config.yaml").write_text(cfgmod.to_yaml(cfg))
    state = Trainer.build(cfg).init()
    checkpoints = Checkpoints(run / "checkpoints", cfg.train.keep_checkpoints)
    try:
        checkpoints.save(0, state, score=0.0)
    finally:
        checkpoints.close()
    return run, cfg, state


def test_cli_exports_a_run_directory(run_dir, tmp_path, capsys):
    run, cfg, state = run_dir
    assert export.main([str(run)]) == 0
    out = run / "export"
    assert sorted(p.name for p in out.iterdir()) == ["policy.json", "policy.npz"]
    assert f"wrote {out / 'policy.npz'} and {out / 'policy.json'}" in capsys.readouterr().out
    loaded = weights.load(out)
    flat = policymod.flatten_params(state.params)
    assert loaded.weights.keys() == flat.keys()
    for name in flat:
        np.testing.assert_array_equal(loaded.weights[name], flat[name])
    assert loaded.header["source"] == {"run_dir": str(run), "checkpoint": "last", "update": 0}
    assert loaded.header["config"]["world"]["size"] == cfg.world.size
    assert loaded.spec.team_size == cfg.robots.count

    # --best and --out: the best checkpoint, written where asked.
    assert export.main([str(run), "--best", "--out", str(tmp_path / "best")]) == 0
    best = json.loads((tmp_path / "best" / "policy.json").read_text())
    assert best["source"]["checkpoint"] == "best"
    assert best["weights"]["sha256"] == loaded.header["weights"]["sha256"]


def test_cli_run_directory_without_checkpoint_fails_in_one_line(tmp_path, capsys):
    cfg = cfgmod.load(REPO / "tests/smoke.yaml")
    (tmp_path / "config.yaml").write_text(cfgmod.to_yaml(cfg))
    assert export.main([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "neither a training run" in err and "\n" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.yaml"]  # nothing written


def test_cli_missing_run_directory_fails_in_one_line(tmp_path):
    missing = tmp_path / "no-such-run"
    result = subprocess.run([sys.executable, "-m", "jaxmripp.export", str(missing)], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip().startswith(f"error: {missing}: no such folder; allowed: a "
                                            "training run")
    assert result.stdout == "" and not missing.exists()


def test_ship_makes_a_folder_eval_loads_like_the_run(run_dir, tmp_path, monkeypatch):
    """A shipped folder (jaxmripp.ship) holds the export, config and metadata, and the
    planner eval.py restores from it acts as the runtime does with the same weights."""
    from jaxmripp import pipeline, ship
    from jaxmripp.sim.observation import Observation, global_state_size
    from jaxmripp.spec.layout import FEATURES, ROBOT_STATE

    run, cfg, _ = run_dir
    (run / "metrics.jsonl").write_text(json.dumps(
        {"update": 10, "env_steps": 960, "seconds": 90.0, "discovered": 0.25, "return": 1.0,
         "entropy": 2.0}) + "\n")
    quality = tmp_path / "quality.jsonl"
    rules = {"config": "configs/protocol_table1.yaml", "worlds": 2}
    quality.write_text('{"name": "quality.command", "value": "python benchmarks/quality.py"}\n'
                       + json.dumps({"name": "quality.rules", "value": rules}) + "\n"
                       '{"name": "quality.policy_pct", "value": 41.5, "unit": "%"}\n'
                       '{"name": "quality.train_minutes", "value": 99.0, "unit": "min"}\n')
    # A preset folder whose `tiny` loads to the run's config but for its name (a run's
    # folder), and another preset that differs from it in one setting.
    packaged = tmp_path / "presets"
    packaged.mkdir()
    (packaged / "tiny.yaml").write_text(f"base: {REPO / 'tests/smoke.yaml'}\n"
                                        "train:\n  name: another_name\n")
    (packaged / "a_wider_one.yaml").write_text(f"base: {REPO / 'tests/smoke.yaml'}\n"
                                               "policy:\n  width: 32\n")
    monkeypatch.setattr(presets, "PRESETS", packaged)
    out = tmp_path / "shipped"
    assert ship.main([str(run), str(out), "--results", str(quality)]) == 0
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["train_minutes"] == 1.5 and meta["updates"] == 10  # from metrics.jsonl
    # The figures with the command and rules they were measured under; the training time
    # is the metrics' (a result file's copy of it is not an evaluation figure).
    assert meta["evaluations"] == [{"results": str(quality), "command":
                                    "python benchmarks/quality.py", "rules": rules,
                                    "figures": {"quality.policy_pct": 41.5}}]
    # The preset the run's config is, by name; without one, the shipped config.yaml.
    assert meta["command"] == "jaxmripp train --config tiny"
    # another seed or start is the same recipe, named as overrides
    reseeded = dataclasses.replace(cfg, train=dataclasses.replace(
        cfg.train, seed=cfg.train.seed + 3, init_from="runs/stage_1"))
    assert ship.training_command(reseeded, out / "config.yaml") == (
        f"jaxmripp train --config tiny train.seed={cfg.train.seed + 3} "
        "train.init_from=runs/stage_1")
    unmatched = dataclasses.replace(cfg, policy=dataclasses.replace(cfg.policy, width=24))
    assert ship.training_command(unmatched, out / "config.yaml") == (
        f"jaxmripp train --config {out / 'config.yaml'}")
    assert "init_from" not in meta
    assert {"policy.npz", "policy.json", "config.yaml", "learning_curve.png"} <= {
        p.name for p in out.iterdir()}

    rng = np.random.default_rng(0)
    n, n_cand = cfg.robots.count, 4 * cfg.candidates.positions
    obs = Observation(
        features=rng.normal(size=(n, n_cand, len(FEATURES))).astype(np.float32),
        mask=rng.random((n, n_cand)) < 0.7,
        robot_state=rng.normal(size=(n, len(ROBOT_STATE))).astype(np.float32),
        global_state=np.zeros((n, global_state_size(n)), np.float32))
    planner = pipeline.trained_planner(cfg, out)
    _, actions = planner.act(None, planner.init(n), obs)
    # The same weights in the NumPy runtime's forward pass pick the same candidates.
    onboard = weights.load(out).policy
    for i in range(n):
        _, logits, _ = onboard(onboard.initial_memory(), obs.features[i], obs.mask[i],
                               obs.robot_state[i])
        assert int(actions[i]) == int(np.argmax(np.where(obs.mask[i], logits, -np.inf)))
    # For a sweep of other settings: the same choices, under its name, with a note.
    notes = []
    sweep_cfg = dataclasses.replace(cfg, sensor=dataclasses.replace(cfg.sensor, range=0.2))
    named = pipeline.sweep_planner(out, sweep_cfg, "mine", log=notes.append)
    assert named.name == "mine"
    np.testing.assert_array_equal(named.act(None, named.init(n), obs)[1], actions)
    assert notes == [f"note: mine was trained with sensor.range={cfg.sensor.range} "
                     "(evaluating with 0.2)"]
    # The metadata alone, again from the shipped folder's own files: the same record.
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.name != "metadata.json"}
    (out / "metadata.json").unlink()
    assert ship.main(["--metadata", str(out), "--results", str(quality),
                      "--commit", meta["commit"]]) == 0
    assert json.loads((out / "metadata.json").read_text()) == meta
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != "metadata.json"} == before
    assert ship.main([str(tmp_path / "nothing"), str(out)]) == 2


def test_a_sweep_builds_the_lookahead_input_its_policies_read(tmp_path):
    from jaxmripp import pipeline

    folders = {}
    for name, cfg in (("plain", CFG), ("ahead", AHEAD)):
        folders[name] = tmp_path / name
        folders[name].mkdir()
        (folders[name] / "config.yaml").write_text(cfgmod.to_yaml(cfg))
    sweep = pipeline.with_policy_inputs(CFG, [folders["ahead"]])
    assert (sweep.policy.ahead_branches, sweep.policy.ahead_discount) == (4, 1.5)
    assert sweep.policy.width == CFG.policy.width  # nothing else is taken over
    assert pipeline.with_policy_inputs(CFG, [folders["plain"]]) == CFG
    with pytest.raises(cfgmod.ConfigError, match="different lookahead inputs"):
        pipeline.with_policy_inputs(CFG, [folders["plain"], folders["ahead"]])
    with pytest.raises(cfgmod.ConfigError, match="reads the lookahead input"):
        pipeline.sweep_planner(folders["ahead"], CFG, "mine")


SHIPPED = sorted(p.name for p in (REPO / "pretrained").iterdir() if p.is_dir())


@pytest.mark.parametrize("name", SHIPPED)
def test_each_shipped_policy_loads_and_flies_by_its_config(name):
    """A folder under pretrained/ is what jaxmripp.ship writes: the export loads (hash,
    layout, widths), the runtime's settings from its header are those its config.yaml
    gives, and metadata.json says how it was trained."""
    folder = REPO / "pretrained" / name
    shipped = weights.load(folder)
    cfg = cfgmod.load(folder / "config.yaml")
    export.check_layout(shipped.header, shipped.weights)
    from_config = export.runtime_spec(cfg)
    assert shipped.spec == from_config
    meta = json.loads((folder / "metadata.json").read_text())
    assert meta["command"].startswith("jaxmripp train --config ")
    assert meta["train_minutes"] > 0 and meta["updates"] > 0
    assert len(meta["commit"]) == 40
