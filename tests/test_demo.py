"""`python -m jaxmripp.demo`: the shipped policy flies a short mission on the NumPy runtime
over the signed team radio, and a bad export or budget gives one error line."""

import re
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxmripp import demo
from jaxmripp.sim import sensing
from jaxmripp.spec.grid import N_HEADINGS

ROOT = Path(__file__).resolve().parents[1]


CAST = jax.jit(jax.vmap(sensing.cast, in_axes=(None, 0, 0, None, None)),
               static_argnums=(3, 4))


def windows_in_view(run, positions, headings):
    """(T,) bool: the windows the simulator's camera sees from these poses."""
    seen = CAST(run.world, np.asarray(positions, np.float32), np.asarray(headings, np.int32),
                run.sensor, int(run.height.shape[0]))
    return np.asarray(seen.seen).any(axis=0)


def test_the_team_finds_more_than_its_take_off_views_and_flies_safe_on_a_signed_radio(capsys):
    # Seed 1: a world where the pads see windows (4 at a full turn; 16 found by flying).
    run = demo.main(["--export", str(ROOT / "pretrained/default_fast"), "--budget", "1",
                     "--seed", "1", "--quiet"])
    out = capsys.readouterr().out
    found = re.search(r"found ([0-9.]+)% of (\d+) windows in (\d+) steps", out)
    assert found, out
    assert float(found.group(1)) == pytest.approx(run.percent, abs=0.05)
    assert int(found.group(2)) == run.valid.sum() and int(found.group(3)) == run.steps >= 2
    # A full turn on every pad sees fewer windows than the team found by flying.
    pads = run.path[0]
    at_pads = np.zeros_like(run.found)
    for turn in range(N_HEADINGS):
        at_pads |= windows_in_view(run, pads, (run.headings[0] + turn) % N_HEADINGS)
    assert run.found.sum() > (at_pads & run.valid).sum() > 0, (run.found.sum(), at_pads.sum())
    # Every window counted was in view of a pose some robot sensed at.
    flown = np.zeros_like(run.found)
    for positions, headings in zip(run.path, run.headings):
        flown |= windows_in_view(run, positions, headings)
    np.testing.assert_array_equal(run.found, flown & run.valid)
    # Every robot flew, and no flight the runtime chose met a building (known-free rule).
    path = np.stack(run.path)  # (rounds, N, 3)
    assert all(len(np.unique(path[:, i], axis=0)) >= 2 for i in range(path.shape[1]))
    assert run.blocked_moves == 0
    # The radio: signed, every message taken by the robots in range, none refused.
    assert all(p.radio.key is not None and p.radio.accepted for p in run.planners)
    assert sum(sum(p.rejected_messages.values()) for p in run.planners) == 0
    assert "radio: signed with the team key" in out and "0 refused" in out


def test_the_tag_is_the_whole_cost_of_signing(capsys):
    """The same run unsigned: the same flights, each message 53 bytes shorter."""
    args = ["--export", str(ROOT / "pretrained/default_fast"), "--budget", "1", "--quiet"]
    signed, unsigned = demo.main(args), demo.main([*args, "--unsigned"])
    capsys.readouterr()
    np.testing.assert_array_equal(np.stack(signed.path), np.stack(unsigned.path))
    for kind in demo.KINDS:
        assert len(signed.message_bytes[kind]) == len(unsigned.message_bytes[kind]) > 0
        np.testing.assert_array_equal(np.subtract(signed.message_bytes[kind],
                                                  unsigned.message_bytes[kind]), 53)
    assert all(p.radio.key is None for p in unsigned.planners)


def test_a_missing_export_gives_one_error_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        demo.main(["--export", str(tmp_path / "absent")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "absent" in err


def test_a_bad_budget_gives_one_error_line(capsys):
    message = "budget: got -1.0; allowed: a positive number"
    with pytest.raises(SystemExit) as exit_info:
        demo.main(["--budget", "-3", "--robots", "3"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err
