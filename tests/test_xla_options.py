"""jaxmripp.sim.xla_options: 512-bit vectors for simulation programs on AVX-512 CPUs only."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmripp.sim import xla_options

CPUINFO = """processor\t: 0
vendor_id\t: GenuineIntel
flags\t\t: fpu sse sse2 avx avx2 {extra}
bugs\t\t: spectre_v1

processor\t: 1
flags\t\t: fpu sse sse2 avx avx2 {extra}
"""


@pytest.fixture
def host(monkeypatch, tmp_path):
    """Sets the host's CPU flags and XLA_FLAGS; returns host_simulation() afresh."""

    def options(extra: str, xla_flags: str | None = None) -> dict:
        info = tmp_path / "cpuinfo"
        info.write_text(CPUINFO.format(extra=extra))
        monkeypatch.setattr(xla_options, "CPUINFO", info)
        if xla_flags is None:
            monkeypatch.delenv("XLA_FLAGS", raising=False)
        else:
            monkeypatch.setenv("XLA_FLAGS", xla_flags)
        xla_options.host_simulation.cache_clear()
        return xla_options.host_simulation()

    yield options
    xla_options.host_simulation.cache_clear()


def test_cpu_flags_reads_the_first_cpus_flags(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text(CPUINFO.format(extra="avx512f avx512bw"))
    flags = xla_options.cpu_flags(info)
    assert {"avx2", "avx512f", "avx512bw"} <= flags and "spectre_v1" not in flags
    assert xla_options.cpu_flags(tmp_path / "absent") == frozenset()


def test_wide_vectors_only_on_avx512_cpus(host):
    assert host("avx512f avx512dq") == {"xla_cpu_prefer_vector_width": 512}
    assert host("avx512_vnni") == {}  # a later AVX-512 extension without the foundation
    assert host("") == {}


def test_a_width_named_in_xla_flags_is_left_alone(host):
    assert host("avx512f", xla_flags="--xla_cpu_prefer_vector_width=256") == {}
    assert host("avx512f", xla_flags="--xla_force_host_platform_device_count=2") == {
        "xla_cpu_prefer_vector_width": 512}


def test_given_options_win_over_the_hosts(host):
    host("avx512f")
    merged = xla_options.simulation({"xla_backend_optimization_level": 0,
                                     "xla_cpu_prefer_vector_width": 128})
    assert merged == {"xla_backend_optimization_level": 0, "xla_cpu_prefer_vector_width": 128}
    assert xla_options.simulation(None) == {"xla_cpu_prefer_vector_width": 512}


def test_xla_compiles_with_the_option_and_computes_the_same_integers(host):
    """The option is one XLA knows, on any x86 or ARM host (a preference, not an ISA
    requirement); integer results do not depend on the vector width."""
    options = host("avx512f")
    x = jnp.arange(10_000, dtype=jnp.int32)

    def fn(v):
        return jnp.cumsum(v % 7) + jnp.sum(v * v)

    wide = jax.jit(fn).lower(x).compile(options)(x)
    np.testing.assert_array_equal(np.asarray(wide), np.asarray(jax.jit(fn)(x)))
