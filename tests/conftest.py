import gc
import os

# The test suite is dominated by compilation. Every program (the tests' own jits too, not only
# jaxlag's) is compiled with the CPU options jaxlag uses for its own programs
# (jaxlag._compile) and, unless JAXLAG_TEST_OPTIMIZED=1, at XLA's backend optimization level
# 0: the results are IEEE arithmetic either way (only rounding may differ, which every tolerance
# here allows for), and the suite takes 7 instead of 10 minutes on 2 workers. Optimized code is
# what `python -m benchmarks` and the examples run; run the suite with JAXLAG_TEST_OPTIMIZED=1
# to test it too. XLA reads XLA_FLAGS when the backend starts (the first computation).
_flags = os.environ.get("XLA_FLAGS", "")
if "xla_cpu_use_fusion_emitters" not in _flags:
    _flags += " --xla_cpu_use_fusion_emitters=false"
# XLA splits each program's LLVM module into parts compiled on a thread pool; on this 2-core
# machine, with 2 pytest workers, those threads only compete, and the split itself costs work:
# compiling each module whole takes 5-10 % less CPU time (measured on test_rigid_bodies,
# test_systems and test_nonconservative, alternating runs). It changes how the code is compiled,
# not the arithmetic (subprocesses the tests start inherit it through XLA_FLAGS).
if "xla_cpu_parallel_codegen_split_count" not in _flags:
    _flags += " --xla_cpu_parallel_codegen_split_count=1"
if os.environ.get("JAXLAG_TEST_OPTIMIZED", "0") != "1" and "xla_backend_optimization_level" not in _flags:
    _flags += " --xla_backend_optimization_level=0"
os.environ["XLA_FLAGS"] = _flags.strip()

# Tracing (the larger part of the suite's time: jvp, partial evaluation and transposition of
# diffrax's loops) allocates millions of short-lived objects, and Python's cyclic garbage
# collector, at its default threshold of 700 allocations, runs through them over and over:
# collecting every 50,000 takes 5-10 % less CPU time on the tracing-heavy tests (measured on
# test_tangent_solve and test_nonconservative, alternating runs). Garbage in reference cycles
# is still freed, a little later.
gc.set_threshold(50_000, 20, 20)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
# Four CPU devices, so that sharded batches are tested in this process (as equinox and diffrax
# test multi-device code); every other test runs on the default device, the first.
jax.config.update("jax_num_cpu_devices", 4)
# As equinox's and diffrax's test suites: implicit rank promotion is an error, so that a
# broadcasting bug in jaxlag (or a test) cannot pass silently.
jax.config.update("jax_numpy_rank_promotion", "raise")
# And, as in equinox's and diffrax's suites, strict dtype promotion: jaxlag never mixes dtypes
# implicitly (an int64 index against an int32 code, a float64 parameter in a float32 run). The
# pages of the docs run with JAX's default ("standard") promotion, as users' scripts do.
jax.config.update("jax_numpy_dtype_promotion", "strict")

# As diffrax's and equinox's suites (their `--jaxtyping-packages=...,beartype.beartype`): every
# function and Module of jaxlag imported from here on is checked against its annotations while
# the tests run, jaxtyping's shapes included ("n" is the same n across one call's arguments).
# The hook rewrites modules as they are imported, so it is installed before anything imports
# jaxlag (this conftest is loaded before the test modules are collected); subprocesses that the
# tests start import jaxlag unchecked. JAXLAG_TEST_TYPECHECK=0 turns it off.
if os.environ.get("JAXLAG_TEST_TYPECHECK", "1") != "0":
    import sys  # noqa: E402

    from jaxtyping import install_import_hook  # noqa: E402

    assert "jaxlag" not in sys.modules, "jaxlag was imported before the type-checking import hook"
    # `float` accepts an int, as it does for the static type checker (PEP 484's numeric tower);
    # every item of a container is checked, as in diffrax's suite (BeartypeStrategy.On).
    install_import_hook(
        "jaxlag",
        "beartype.beartype(conf=beartype.BeartypeConf("
        "is_pep484_tower=True, strategy=beartype.BeartypeStrategy.On))",
    )

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test module.

    Every compiled XLA CPU program holds about ten memory mappings for as long as JAX's caches
    keep it. The whole suite in one process (``pytest -n0``) compiles enough programs to pass
    Linux's limit of 65,530 mappings per process (``vm.max_map_count``), and XLA then crashed
    with a segmentation fault while compiling (seen twice at 97 % of the suite, mappings
    growing ~90 per test). After each module only that module's programs are alive.
    """
    yield
    jax.clear_caches()
    gc.collect()
