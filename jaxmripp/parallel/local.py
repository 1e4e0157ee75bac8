"""Several processes of one run on this machine (tests, benchmarks and trying a launch).

    python -m jaxmripp.parallel.local 2 train.py --config tests/smoke.yaml

starts `python train.py ... --processes 2 --process-id I --coordinator 127.0.0.1:PORT`
for I = 0, 1 on a free port pair, prints process 0's output and returns the first failing
exit status (0 if all succeeded).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from typing import Any, Sequence

import numpy as np

def host_devices_env(devices: int, env: dict[str, str] | None = None) -> dict[str, str]:
    """`env` (default: this process's) for a child with `devices` CPU devices and only
    the CPU platform; other XLA flags are kept."""
    env = dict(os.environ if env is None else env)
    flags = [f for f in env.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join([*flags, f"--xla_force_host_platform_device_count={devices}"])
    env["JAX_PLATFORMS"] = "cpu"
    return env



def free_port_pair() -> int:
    """A port P with P and P + 1 free on 127.0.0.1 (the coordinator and the check-in)."""
    for _ in range(50):
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        if port >= 65534:
            continue
        try:
            with socket.socket() as a, socket.socket() as b:
                a.bind(("127.0.0.1", port))
                b.bind(("127.0.0.1", port + 1))
            return port
        except OSError:
            continue
    raise RuntimeError("no free pair of adjacent ports on 127.0.0.1")


def run_local(command: Sequence[str], processes: int, timeout_s: float = 600.0,
              env: dict[str, str] | None = None,
              launch_timeout_s: float = 60.0) -> list[subprocess.CompletedProcess]:
    """Runs `python COMMAND --processes P --process-id I --coordinator 127.0.0.1:PORT` for
    every I at once, each with one CPU device and `env` (default: this process's);
    returns their completed processes (stdout and stderr captured)."""
    port = free_port_pair()
    child_env = host_devices_env(1, env)  # one CPU device per process
    children = [subprocess.Popen(
        [sys.executable, *command, "--processes", str(processes), "--process-id", str(i),
         "--coordinator", f"127.0.0.1:{port}", "--launch-timeout", str(launch_timeout_s)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=child_env)
        for i in range(processes)]
    done = []
    try:
        for child in children:
            out, err = child.communicate(timeout=timeout_s)
            done.append(subprocess.CompletedProcess(child.args, child.returncode, out, err))
    finally:
        for child in children:
            if child.poll() is None:
                child.kill()
    return done


def max_relative_difference(a: Any, b: Any) -> float:
    """max |a - b| / max |b| over every parameter of two runs (pytrees of one structure):
    the infinity-norm relative difference of the flattened parameter vectors. (Per leaf it
    would be ill-posed: some leaves, such as attention key biases, get no gradient and stay
    at rounding noise around zero.)"""
    import jax  # noqa: PLC0415 (the launcher itself must not start JAX)

    pairs = list(zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))
    largest = max(float(np.max(np.abs(np.asarray(y)))) for _, y in pairs)
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in pairs) / max(
        largest, 1e-12)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if len(argv) < 2 or not argv[0].isdigit() or int(argv[0]) < 1:
        print("usage: python -m jaxmripp.parallel.local PROCESSES SCRIPT [ARGS ...]",
              file=sys.stderr)
        return 2
    results = run_local(argv[1:], int(argv[0]))
    print(results[0].stdout, end="")
    for i, result in enumerate(results):
        if result.returncode:
            print(f"process {i} exited with {result.returncode}:\n{result.stderr[-2000:]}",
                  file=sys.stderr)
    return next((r.returncode for r in results if r.returncode), 0)


if __name__ == "__main__":
    sys.exit(main())
