"""`python -m jaxmripp.demo`: the shipped policy flies a short mission on the NumPy runtime,
and a bad export or sector count gives one error line."""

import re
from pathlib import Path

import pytest

from jaxmripp import demo

ROOT = Path(__file__).resolve().parents[1]


def test_shipped_policy_finds_windows_in_a_short_mission(capsys):
    percent = demo.main(["--export", str(ROOT / "pretrained/default_fast"), "--budget", "1",
                         "--quiet"])
    out = capsys.readouterr().out
    found = re.search(r"found ([0-9.]+)% of (\d+) windows in (\d+) steps", out)
    assert found, out
    assert float(found.group(1)) == pytest.approx(percent, abs=0.05)
    # Windows come into view from the take-off scan and every step after it.
    assert 0.0 < percent <= 100.0 and int(found.group(3)) >= 1


def test_a_missing_export_gives_one_error_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        demo.main(["--export", str(tmp_path / "absent")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "absent" in err


@pytest.mark.parametrize("flags, message", [
    (["--sector-count", "2"], "sector_count: got 2; it needs sectors=True"),
    (["--sectors", "--sector-count", "4"], "sector_count: got 4; allowed: an integer 0 .. 3"),
], ids=["without_sectors", "more_than_robots"])
def test_a_bad_sector_count_gives_one_error_line(capsys, flags, message):
    with pytest.raises(SystemExit) as exit_info:
        demo.main([*flags, "--robots", "3"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err
