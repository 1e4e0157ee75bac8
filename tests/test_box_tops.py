"""Box tops (`sensor.gain_tops=boxes`, `jaxmripp.spec.view`): the JAX rule
(`jaxmripp.sim.tops.box_tops`) and the runtime's (`jaxmripp.runtime.view.box_tops`)
against a reference that walks the written rule box by box, on random maps and on a
building seen from one side; the env keeps each map's tops and lowest FREE z step by
step and hands their box tops to the view gain."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp import config
from jaxmripp.runtime import view as runtime_view
from jaxmripp.sim import env as envmod, tops
from jaxmripp.spec.grid import FREE, OCCUPIED, UNKNOWN

ROOT = Path(__file__).resolve().parents[1]


def column_bounds(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(..., G, G, G) codes -> each column's top and lowest FREE z, one column at a time."""
    size = codes.shape[-1]
    top = np.zeros(codes.shape[:-1], np.int8)
    lowest_free = np.full(codes.shape[:-1], size, np.int8)
    for column in np.ndindex(codes.shape[:-1]):
        occupied = np.flatnonzero(codes[column] == OCCUPIED)
        free = np.flatnonzero(codes[column] == FREE)
        top[column] = occupied.max() + 1 if len(occupied) else 0
        lowest_free[column] = free.min() if len(free) else size
    return top, lowest_free


def reference(codes: np.ndarray, side: int) -> np.ndarray:
    """The spec's rule, one box and one column at a time."""
    size = codes.shape[0]
    top, lowest_free = column_bounds(codes)
    completed = top.copy()
    for x in range(size - side + 1):
        for y in range(size - side + 1):
            box = (slice(x, x + side), slice(y, y + side))
            highest = top[box].max()
            if highest > 0 and np.all(lowest_free[box] >= highest):
                completed[box] = np.maximum(completed[box], highest)
    return completed


def jax_box_tops(codes: np.ndarray, side: int) -> np.ndarray:
    """The JAX box tops of a whole map, from its tops and lowest FREE z."""
    return np.asarray(tops.box_tops(*map(jnp.asarray, column_bounds(codes)), side))


def runtime_box_tops(codes: np.ndarray, side: int) -> np.ndarray:
    """The runtime's box tops of a whole map: its tops (kept by the map: here read whole)
    and the lowest FREE z it reads from the codes."""
    size = codes.shape[0]
    top, _ = column_bounds(codes)
    return runtime_view.box_tops(top, runtime_view.lowest_free(codes.reshape(-1), size), side)


@pytest.mark.parametrize("seed", range(4))
def test_both_sides_follow_the_written_rule_on_random_maps(seed):
    rng = np.random.default_rng(seed)
    for _ in range(12):
        size, side = int(rng.integers(4, 12)), int(rng.integers(1, 5))
        codes = rng.choice(np.array([FREE, UNKNOWN, OCCUPIED], np.int8), size=(size,) * 3,
                           p=rng.dirichlet([1.0, 1.0, 1.0]))
        want = reference(codes, side)
        np.testing.assert_array_equal(jax_box_tops(codes, side), want)
        np.testing.assert_array_equal(runtime_box_tops(codes, side), want)


def _one_column_seen(size=12, height=4):
    """A map that knows one column (5, 5) of a building up to z = height - 1 and the
    columns x = 4 and y = 4 free at every height."""
    codes = np.full((size,) * 3, UNKNOWN, np.int8)
    codes[5, 5, :height] = OCCUPIED
    codes[4], codes[:, 4] = FREE, FREE
    return codes


def test_a_column_seen_from_a_corner_completes_the_one_box_it_allows():
    codes = _one_column_seen()
    want = np.zeros((12, 12), np.int8)
    want[5:8, 5:8] = 4
    np.testing.assert_array_equal(jax_box_tops(codes, 3), want)
    # Free above the known top does not rule a column out; free below it does, and then
    # the box tops fall to what the boxes left allow.
    codes[7, 7, 4:] = FREE
    np.testing.assert_array_equal(jax_box_tops(codes, 3), want)
    codes[7, 7, 2] = FREE
    fallen = jax_box_tops(codes, 3)
    assert fallen[5, 5] == 4 and fallen[7, 7] == 0 and fallen.sum() < want.sum()
    np.testing.assert_array_equal(fallen, reference(codes, 3))


def test_the_env_keeps_each_maps_tops_and_the_gain_reads_their_box_tops():
    """Episodes a few random flights in with box tops (the lookahead tests' episodes, so
    they compile once for both files): the tops and lowest FREE z the env keeps step by
    step (casts, bumps, shared maps) are those of each robot's whole map, and view_top is
    the box tops of each robot's map."""
    from test_lookahead import _run_episodes

    cfg, (_, state, _) = _run_episodes("view", 3)
    assert cfg.sensor.gain_tops == "boxes" and cfg.radio.share_maps
    whole_top, whole_free = column_bounds(np.asarray(state.occupancy))
    np.testing.assert_array_equal(state.building_top, whole_top)
    np.testing.assert_array_equal(state.lowest_free, whole_free)
    side = cfg.world.footprint_min or cfg.world.footprint
    maps = np.asarray(state.occupancy)
    for e, i in np.ndindex(maps.shape[:2]):
        np.testing.assert_array_equal(state.view_top[e, i], reference(maps[e, i], side))
    assert np.any(whole_top > 0) and np.any(whole_free < cfg.world.size)
    assert np.any(np.asarray(state.view_top) > whole_top)  # the boxes added columns


def test_either_tops_give_the_same_maps_and_mapped_reads_the_maps_tops():
    """Reset from one key with either setting (one compilation for both): the same maps,
    tops and lowest FREE z; the gain reads the map's tops, or their box tops."""
    key = jax.random.key(5)
    configs = {setting: config.load(ROOT / "tests" / "smoke.yaml",
                                    [f"sensor.gain_tops={setting}"])
               for setting in ("mapped", "boxes")}
    params = {s: (envmod.EnvParams.from_config(c), envmod.DynamicParams.from_config(c))
              for s, c in configs.items()}
    states = jax.jit(lambda k: {s: envmod.reset(k, *p)[1] for s, p in params.items()})(key)
    mapped, boxes = states["mapped"], states["boxes"]
    for field in ("team_map", "building_top", "lowest_free"):
        np.testing.assert_array_equal(getattr(mapped, field), getattr(boxes, field))
    np.testing.assert_array_equal(mapped.view_top, mapped.building_top)
    side = configs["boxes"].world.footprint_min or configs["boxes"].world.footprint
    for i, codes in enumerate(np.asarray(boxes.occupancy)):
        np.testing.assert_array_equal(boxes.view_top[i], reference(codes, side))
    assert np.any(boxes.building_top > 0)  # the robots start seeing some building


def test_an_export_carries_the_box_side_and_the_runtime_needs_it():
    from jaxmripp import export
    from jaxmripp.runtime import weights
    from jaxmripp.runtime.errors import WeightsFormatError

    cfg = config.load(ROOT / "tests" / "smoke.yaml",
                      ["sensor.gain_tops=boxes", "world.footprint=4", "world.footprint_min=2"])
    spec = export.runtime_spec(cfg)
    assert (spec.gain.tops, spec.gain.box_side) == ("boxes", 2)  # the smallest footprint
    head = weights.jsonable(export.header(cfg))
    del head["config"]["world"]["box_side"]
    with pytest.raises(WeightsFormatError, match="world.*box_side"):
        weights.RuntimeSpec.from_header(head)
    mapped = config.load(ROOT / "tests" / "smoke.yaml")
    assert "box_side" not in export.header(mapped)["config"]["world"]
    assert export.runtime_spec(mapped).gain.tops == "mapped"
