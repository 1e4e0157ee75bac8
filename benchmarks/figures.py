"""The JSON lines benchmarks print, each naming the machine it was measured on.

Standard library only, so that `runtime.py`, which must not import jax, prints the same
lines as the scripts that go through `common.emit`.
"""

from __future__ import annotations

import functools
import json
import os
import sys
from typing import Any


def line(name: str, value: Any, unit: str | None = None, *, device: str, **extra: Any) -> str:
    """One figure as a JSON object: name, value, unit (if any), extra fields, device."""
    record: dict[str, Any] = {"name": name, "value": value}
    if unit is not None:
        record["unit"] = unit
    return json.dumps({**record, **extra, "device": device})


def emit(name: str, value: float, unit: str, *, device: str, **extra: Any) -> None:
    """Prints one figure (rounded to 4 decimals) as a JSON line, flushed at once."""
    print(line(name, round(float(value), 4), unit, device=device, **extra))
    sys.stdout.flush()


@functools.cache
def host_cpu() -> str:
    """The host CPU as "<cores>-core <vendor> <family>" (e.g. "2-core Intel Xeon"), the
    family read from /proc/cpuinfo where there is one."""
    model = ""
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            model = next((entry.split(":", 1)[1] for entry in cpuinfo
                          if entry.startswith("model name")), "")
    except OSError:
        pass
    return f"{os.cpu_count()}-core {cpu_family(model)}".rstrip()


def cpu_family(model: str) -> str:
    """A CPU's vendor and family from its model name, without trademarks, clock and core
    count: "Intel(R) Xeon(R) Processor" -> "Intel Xeon", "AMD EPYC 9R14 96-Core Processor"
    -> "AMD EPYC"; the first two words of anything else."""
    words = [w for w in model.replace("(R)", " ").replace("(TM)", " ").split()
             if w not in ("CPU", "Processor", "@")]
    return " ".join(words[:2])
