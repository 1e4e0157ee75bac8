"""Progress on the terminal: shown on a terminal only, never when quiet."""

import io
import re
import sys
from pathlib import Path

import pytest

from jaxmripp.parallel import progress

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _stderr(monkeypatch, tty: bool = True) -> io.StringIO:
    """stderr replaced for the test (in its body: pytest's capture resets stderr between
    a fixture's setup and the test)."""
    screen = Terminal() if tty else io.StringIO()
    monkeypatch.setattr(sys, "stderr", screen)
    return screen


def test_a_compilation_shows_its_line_and_seconds_on_a_terminal(monkeypatch):
    screen = _stderr(monkeypatch)
    with progress.compiling("the training chunk (5 updates)") as timer:
        pass
    assert re.fullmatch(r"compiling the training chunk \(5 updates\) \.\.\. \d+\.\d s\n",
                        screen.getvalue())
    assert timer.seconds >= 0


def test_the_bar_counts_with_an_eta_and_lines_go_above_it(monkeypatch):
    screen = _stderr(monkeypatch)
    write = progress.above(lambda line: screen.write(line + "\n"))
    with progress.bar(10, "training", initial=4, unit="update") as bar:
        bar.update(3)
        write("chunk 2/3")
        assert bar.n == 7
    shown = screen.getvalue()
    # the line written once, clear of the bar: the bar is redrawn after it
    assert shown.count("chunk 2/3\n") == 1
    last = shown.split("chunk 2/3\n")[1]
    assert re.search(r"training: +70%.*7/10 \[\d\d:\d\d<\d\d:\d\d", last), last


@pytest.mark.parametrize("quiet, tty", [(True, True), (False, False)])
def test_nothing_is_shown_when_quiet_or_off_a_terminal(monkeypatch, quiet, tty):
    screen = _stderr(monkeypatch, tty)
    with progress.compiling("x", quiet=quiet) as timer:
        with progress.bar(3, "training", quiet=quiet) as bar:
            bar.update(3)
    assert screen.getvalue() == "" and timer.seconds >= 0


def test_a_quiet_process_shows_nothing_until_shown_again(monkeypatch):
    screen = _stderr(monkeypatch)
    progress.set_quiet()
    try:
        with progress.compiling("x"), progress.bar(3, "sweep") as bar:
            bar.update(3)
        assert screen.getvalue() == ""
    finally:
        progress.set_quiet(False)
    with progress.bar(3, "sweep") as bar:
        bar.update(3)
    assert "sweep" in screen.getvalue()


@pytest.mark.parametrize("script", ["quality", "scale", "ablation", "flight", "generalize"])
def test_each_long_benchmark_takes_quiet(script, monkeypatch, capsys):
    """--quiet of a long benchmark silences the process's bars before any work starts (its
    parser is stopped right after, by a bad value of another flag)."""
    import importlib

    monkeypatch.syspath_prepend(str(BENCHMARKS))
    module = importlib.import_module(script)
    monkeypatch.setattr(progress, "_QUIET", False)
    with pytest.raises(SystemExit) as stopped:
        module.main(["--quiet", "--no-such-flag"])
    assert stopped.value.code == 2
    assert "error: unrecognized arguments: --no-such-flag" in capsys.readouterr().err
    assert progress._QUIET is True
