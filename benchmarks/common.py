"""Timing helpers for the jaxlag benchmarks.

Import this module *before* ``jax``: it pins the process to one core and sets ``XLA_FLAGS`` so
that XLA runs single-threaded, then enables float64. The machine is shared and noisy, so:

* contenders are timed alternately (A, B, C, A, B, C, ...), ``repeats`` rounds, and the median
  of each is quoted;
* every sample runs the compiled function enough times to last ``min_sample_s`` (timer
  resolution and dispatch overhead become negligible);
* ratios are taken against a hand-written baseline measured in the same run and the same
  rounds: they are the numbers that count, absolute times drift with the load.

Compile time is reported separately: ``jax.jit(f).lower(*args)`` (tracing) plus ``.compile()``
(XLA), measured once.
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

if "jax" in sys.modules:  # pragma: no cover - a guard for misuse
    print("warning: benchmarks.common imported after jax; XLA_FLAGS may not take effect", file=sys.stderr)


def _pin_to_last_core() -> int | None:
    try:
        cores = sorted(os.sched_getaffinity(0))
        core = cores[-1]
        os.sched_setaffinity(0, {core})
        return core
    except (AttributeError, OSError):  # not Linux
        return None


CORE = _pin_to_last_core()
_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
# Compile times are measured from scratch: jaxlag turns on no persistent compilation cache
# unless asked (jl.enable_compilation_cache), and this process does not ask.
if _FLAGS not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _FLAGS).strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

#: Environment knobs: BENCH_REPEATS overrides the number of alternating rounds,
#: BENCH_QUICK=1 shrinks everything to a smoke test.
QUICK = os.environ.get("BENCH_QUICK", "0") not in ("", "0")
REPEATS = int(os.environ.get("BENCH_REPEATS", "3" if QUICK else "11"))


@dataclass
class Contender:
    """One compiled function and its inputs."""

    name: str
    compiled: Callable
    args: tuple
    trace_s: float
    xla_s: float
    calls_per_sample: int = 1
    samples: list = field(default_factory=list)

    @property
    def compile_s(self) -> float:
        return self.trace_s + self.xla_s

    @property
    def median(self) -> float:
        """Median seconds per call."""
        return statistics.median(self.samples)


def compile_contender(name: str, fn: Callable, *args: Any) -> Contender:
    """``jax.jit(fn)``, lowered and compiled ahead of time; the times of both are recorded."""
    start = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    traced = time.perf_counter()
    compiled = lowered.compile()
    done = time.perf_counter()
    jax.block_until_ready(compiled(*args))  # first call: allocations, page faults
    return Contender(name, compiled, args, traced - start, done - traced)


def _calibrate(c: Contender, min_sample_s: float) -> None:
    start = time.perf_counter()
    jax.block_until_ready(c.compiled(*c.args))
    one = time.perf_counter() - start
    c.calls_per_sample = max(1, int(min_sample_s / max(one, 1e-9)) + 1)


def _sample(c: Contender) -> float:
    start = time.perf_counter()
    for _ in range(c.calls_per_sample):
        out = c.compiled(*c.args)
    jax.block_until_ready(out)
    return (time.perf_counter() - start) / c.calls_per_sample


def time_alternating(
    contenders: Sequence[Contender], repeats: int = REPEATS, min_sample_s: float = 0.02
) -> None:
    """Fill ``c.samples`` (seconds per call) for each contender, alternating between them."""
    for c in contenders:
        _calibrate(c, min_sample_s)
        c.samples = []
    for _ in range(repeats):
        for c in contenders:
            c.samples.append(_sample(c))


def spread(c: Contender) -> float:
    """Relative half-width of the inter-quartile range, a noise indicator."""
    if len(c.samples) < 4:
        return float("nan")
    q = statistics.quantiles(c.samples, n=4)
    return 0.5 * (q[2] - q[0]) / c.median


def print_table(title: str, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """A plain fixed-width table."""
    cells = [[_fmt(x) for x in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(header)]
    line = "  ".join(h.rjust(w) if i else h.ljust(w) for i, (h, w) in enumerate(zip(header, widths)))
    print()
    print(title)
    print(line)
    print("-" * len(line))
    for r in cells:
        print("  ".join(x.rjust(w) if i else x.ljust(w) for i, (x, w) in enumerate(zip(r, widths))))
    sys.stdout.flush()


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        if x != x:
            return "-"
        if abs(x) >= 100:
            return f"{x:.0f}"
        if abs(x) >= 10:
            return f"{x:.1f}"
        return f"{x:.2f}"
    return str(x)


def environment_line() -> str:
    import diffrax

    return (
        f"jax {jax.__version__}, diffrax {diffrax.__version__}, backend "
        f"{jax.default_backend()}, pinned to core {CORE}, XLA_FLAGS='{os.environ['XLA_FLAGS']}', "
        f"{REPEATS} alternating rounds, medians"
    )


def max_abs_diff(a, b) -> float:
    return float(jnp.max(jnp.abs(jnp.asarray(a) - jnp.asarray(b))))
