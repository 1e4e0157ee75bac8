"""Multi-process launches: the check-in, and bad launches ending with one line within
seconds. (Training on 2 devices and 2 processes is compared with 1 device in
test_train.py, evaluation on 2 devices in test_evaluate.py: they hold the 1-device runs.)"""

import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from jaxmripp.parallel import launch
from jaxmripp.parallel.local import free_port_pair, host_devices_env, max_relative_difference

TRAIN_SMOKE = ["train.py", "--config", "tests/smoke.yaml", "--no-eval"]


def test_relative_difference_by_hand():
    a = {"w": np.array([1.0, -2.0]), "b": np.array([0.5])}
    b = {"w": np.array([1.0, -4.0]), "b": np.array([0.25])}
    assert max_relative_difference(a, b) == pytest.approx(2.0 / 4.0)


def test_training_refuses_a_batch_the_devices_cannot_split(tmp_path):
    done = subprocess.run([sys.executable, *TRAIN_SMOKE, "--runs", str(tmp_path)],
                          env=host_devices_env(3),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "error: train.envs = 4 cannot be split over 3 devices; allowed: a multiple of 3 "
        "(1 process(es) x 3 local device(s))"]


def test_unreachable_coordinator_fails_within_seconds_with_one_line(tmp_path):
    port = free_port_pair()
    start = time.monotonic()
    done = subprocess.run(
        [sys.executable, *TRAIN_SMOKE, "--runs", str(tmp_path), "--processes", "2",
         "--process-id", "1",
         "--coordinator", f"127.0.0.1:{port}", "--launch-timeout", "2"],
        capture_output=True, text=True, timeout=60)
    assert time.monotonic() - start < 20
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"error: process 1: cannot reach process 0 at 127.0.0.1:{port + 1} within 2 s; is it "
        "running, and is --coordinator its HOST:PORT?"]


def _check_in_error(settings: launch.Launch) -> str:
    """The check-in of one process (process 0 gathers): its error line, or ""."""
    deadline = time.monotonic() + settings.timeout_s
    try:
        if settings.process_id == 0:
            launch._gather(settings, deadline)
        else:
            launch._check_in(settings, deadline)
    except launch.LaunchError as err:
        return str(err)
    return ""


def _launch_in_thread(settings: launch.Launch, errors: dict) -> threading.Thread:
    """Runs the check-in in a thread; a failure goes to errors[process id]."""
    def check_in():
        if error := _check_in_error(settings):
            errors[settings.process_id] = error

    thread = threading.Thread(target=check_in)
    thread.start()
    return thread


def test_check_in_agrees_when_every_process_arrives():
    address = f"127.0.0.1:{free_port_pair()}"
    errors = {}
    threads = [_launch_in_thread(launch.Launch(3, i, address, 5.0), errors) for i in range(3)]
    for thread in threads:
        thread.join()
    assert errors == {}


def test_check_in_names_a_missing_process():
    address = f"127.0.0.1:{free_port_pair()}"
    errors = {}
    threads = [_launch_in_thread(launch.Launch(3, i, address, 1.0), errors) for i in (0, 2)]
    for thread in threads:
        thread.join()
    assert errors[0] == ("only 2 of 3 processes checked in within 1 s (missing ids: 1); is "
                         "--processes right?")
    assert errors[2] == errors[0]


def test_check_in_names_a_wrong_process_count():
    address = f"127.0.0.1:{free_port_pair()}"
    errors = {}
    threads = [_launch_in_thread(launch.Launch(2, 0, address, 5.0), errors),
               _launch_in_thread(launch.Launch(3, 1, address, 5.0), errors)]
    for thread in threads:
        thread.join()
    assert errors == {0: "process 1 was started with --processes 3, process 0 with 2",
                      1: "process 1 was started with --processes 3, process 0 with 2"}


def test_check_in_names_a_repeated_process_id():
    address = f"127.0.0.1:{free_port_pair()}"
    errors = {}
    first = _launch_in_thread(launch.Launch(3, 0, address, 5.0), errors)
    repeated = [[], []]
    threads = [threading.Thread(target=lambda out=out: out.append(_check_in_error(
        launch.Launch(3, 1, address, 5.0)))) for out in repeated]
    for thread in threads:
        thread.start()
    for thread in [first, *threads]:
        thread.join()
    message = "two processes were started with --process-id 1"
    assert errors == {0: message} and repeated == [[message], [message]]


@pytest.mark.parametrize("kwargs, message", [
    (dict(processes=0), "--processes: got 0; allowed: 1 or more"),
    (dict(processes=2, process_id=2, coordinator="h:1"),
     "--process-id: got 2; allowed: 0 .. 1 for 2 processes"),
    (dict(processes=2, coordinator="nohost"),
     "--coordinator: got 'nohost'; allowed: HOST:PORT of process 0 (PORT and PORT + 1 must "
     "be free)"),
])
def test_launch_settings_are_checked(kwargs, message):
    with pytest.raises(launch.LaunchError) as err:
        launch.Launch(**kwargs)
    assert str(err.value) == message
