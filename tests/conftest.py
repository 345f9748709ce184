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
if os.environ.get("JAXLAG_TEST_OPTIMIZED", "0") != "1" and "xla_backend_optimization_level" not in _flags:
    _flags += " --xla_backend_optimization_level=0"
os.environ["XLA_FLAGS"] = _flags.strip()

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
