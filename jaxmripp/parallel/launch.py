"""Starting one run over several processes (hosts): a check-in, then `jax.distributed`.

Every process gets the same command plus its own id, e.g. for two processes

    python train.py --processes 2 --process-id 0 --coordinator HOST:PORT ...   # on HOST
    python train.py --processes 2 --process-id 1 --coordinator HOST:PORT ...   # elsewhere

(or the environment variables JAX_COORDINATOR_ADDRESS, JAXMRIPP_PROCESSES and
JAXMRIPP_PROCESS_ID). JAX's coordination service aborts the whole process with a stack
trace when a peer never arrives; so before it starts, the processes check in with process
0 on the port after the coordinator's: process 0 waits for every other id, and everyone
agrees on the process count. A wrong count, a repeated id or an unreachable coordinator
then ends every process with one line (`LaunchError`) within `timeout_s`.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import socket
import time

import jax
from jax.experimental import multihost_utils

ENV_COORDINATOR = "JAX_COORDINATOR_ADDRESS"  # JAX's own name
ENV_PROCESSES = "JAXMRIPP_PROCESSES"
ENV_PROCESS_ID = "JAXMRIPP_PROCESS_ID"
GREETING = "jaxmripp-launch 1"
REPLY_GRACE_S = 5.0  # how much longer than --launch-timeout a process waits for process 0


class LaunchError(RuntimeError):
    """A multi-process launch that cannot start; the message is one line."""


@dataclasses.dataclass(frozen=True)
class Launch:
    processes: int = 1
    process_id: int = 0
    coordinator: str = ""  # HOST:PORT of process 0; the check-in uses PORT + 1
    timeout_s: float = 60.0

    def __post_init__(self):
        if self.processes < 1:
            raise LaunchError(f"--processes: got {self.processes}; allowed: 1 or more")
        if not 0 <= self.process_id < self.processes:
            raise LaunchError(f"--process-id: got {self.process_id}; allowed: 0 .. "
                              f"{self.processes - 1} for {self.processes} processes")
        if self.processes > 1:
            host, sep, port = self.coordinator.rpartition(":")
            if not sep or not host or not port.isdigit() or not 0 < int(port) < 65535:
                raise LaunchError(f"--coordinator: got {self.coordinator!r}; allowed: "
                                  "HOST:PORT of process 0 (PORT and PORT + 1 must be free)")
        if self.timeout_s <= 0:
            raise LaunchError(f"--launch-timeout: got {self.timeout_s}; allowed: > 0 seconds")

    @property
    def address(self) -> tuple[str, int]:
        host, _, port = self.coordinator.rpartition(":")
        return host.strip("[]"), int(port) + 1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("multi-process launch (docs/distributed.md)")
    group.add_argument("--processes", type=int, default=None,
                       help=f"processes in the run (default ${ENV_PROCESSES} or 1)")
    group.add_argument("--process-id", type=int, default=None,
                       help=f"this process, 0 .. processes - 1 (default ${ENV_PROCESS_ID} or 0)")
    group.add_argument("--coordinator", default=None,
                       help=f"HOST:PORT of process 0 (default ${ENV_COORDINATOR})")
    group.add_argument("--launch-timeout", type=float, default=60.0,
                       help="seconds to wait for every process to check in")


def from_arguments(args: argparse.Namespace) -> Launch:
    def pick(value, env: str, default):
        if value is not None:
            return value
        text = os.environ.get(env)
        if text is None:
            return default
        if isinstance(default, int):
            try:
                return int(text)
            except ValueError:
                raise LaunchError(f"${env}: got {text!r}; allowed: an integer") from None
        return text

    return Launch(pick(args.processes, ENV_PROCESSES, 1),
                  pick(args.process_id, ENV_PROCESS_ID, 0),
                  pick(args.coordinator, ENV_COORDINATOR, ""), args.launch_timeout)


def initialize(launch: Launch) -> None:
    """Checks in with the other processes, then starts JAX's distributed runtime; nothing
    happens for a single process. Call before anything touches a JAX device."""
    if launch.processes == 1:
        return
    deadline = time.monotonic() + launch.timeout_s
    if launch.process_id == 0:
        _gather(launch, deadline)
    else:
        _check_in(launch, deadline)
    jax.distributed.initialize(launch.coordinator, launch.processes, launch.process_id,
                               initialization_timeout=max(1, round(launch.timeout_s)))


def barrier(name: str) -> None:
    """Waits for every process (nothing to wait for in a single-process run)."""
    if jax.process_count() > 1:
        multihost_utils.sync_global_devices(name)


def _gather(launch: Launch, deadline: float) -> None:
    """Process 0: wait for ids 1 .. processes - 1, then tell everyone whether to go on."""
    peers: dict[int, socket.socket] = {}
    extra: list[socket.socket] = []  # a second process with an id already checked in
    problem = ""
    try:
        server = socket.create_server(("", launch.address[1]))
    except OSError as err:
        raise LaunchError(f"process 0: cannot listen on port {launch.address[1]} for the "
                          f"check-in ({err.strerror}); choose another --coordinator port"
                          ) from None
    with server:
        while len(peers) < launch.processes - 1 and not problem:
            server.settimeout(max(deadline - time.monotonic(), 0.01))
            try:
                conn, _ = server.accept()
            except (TimeoutError, socket.timeout):
                missing = sorted(set(range(1, launch.processes)) - set(peers))
                problem = (f"only {len(peers) + 1} of {launch.processes} processes checked in "
                           f"within {launch.timeout_s:g} s (missing ids: "
                           f"{', '.join(map(str, missing))}); is --processes right?")
                break
            words = _read_line(conn, deadline).split()
            if (len(words) != 4 or " ".join(words[:2]) != GREETING
                    or not (words[2].isdigit() and words[3].isdigit())):
                conn.close()  # not one of ours
                continue
            pid, count = int(words[2]), int(words[3])
            if count != launch.processes:
                problem = (f"process {pid} was started with --processes {count}, process 0 "
                           f"with {launch.processes}")
            elif pid in peers or pid == 0:
                problem = f"two processes were started with --process-id {pid}"
            if pid in peers:
                extra.append(conn)
            else:
                peers[pid] = conn
        reply = f"error: {problem}" if problem else "ok"
        for conn in [*peers.values(), *extra]:
            try:
                conn.sendall((reply + "\n").encode())
            finally:
                conn.close()
    if problem:
        raise LaunchError(problem)


def _check_in(launch: Launch, deadline: float) -> None:
    """Other processes: connect to process 0 (retrying until the deadline), wait for go."""
    host, port = launch.address
    while True:
        try:
            conn = socket.create_connection((host, port), timeout=1.0)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise LaunchError(f"process {launch.process_id}: cannot reach process 0 at "
                                  f"{host}:{port} within {launch.timeout_s:g} s; is it "
                                  "running, and is --coordinator its HOST:PORT?") from None
            time.sleep(0.2)
    with conn:
        conn.sendall(f"{GREETING} {launch.process_id} {launch.processes}\n".encode())
        # process 0 answers at the latest at its own deadline, which may be a little later
        reply = _read_line(conn, deadline + REPLY_GRACE_S)
    if reply != "ok":
        raise LaunchError(reply.removeprefix("error: ") or
                          f"process {launch.process_id}: process 0 closed the check-in")


def _read_line(conn: socket.socket, deadline: float) -> str:
    data = b""
    while not data.endswith(b"\n"):
        conn.settimeout(max(deadline - time.monotonic(), 0.01))
        try:
            chunk = conn.recv(256)
        except (TimeoutError, socket.timeout, OSError):
            break
        if not chunk:
            break
        data += chunk
    return data.decode(errors="replace").strip()
