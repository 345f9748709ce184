"""Run every jaxlag benchmark and print the ratio tables.

``python -m benchmarks`` (or ``python -m benchmarks.run_all``) from the repository root: one
process, every section, then the list of targets (issue 7) marked ``ok`` or ``MISS``.
"""

from __future__ import annotations

import time

from . import (
    bench_batch,
    bench_compile,
    bench_constrained,
    bench_gradient,
    bench_sympy,
    bench_unconstrained,
    common,  # first: pins the core and sets XLA_FLAGS before jax is imported
)
from .verdicts import best_hand_verdicts, print_verdicts


def main() -> None:
    start = time.perf_counter()
    print(common.environment_line())
    verdicts = bench_unconstrained.run()
    verdicts += best_hand_verdicts(bench_constrained.run())
    verdicts += bench_compile.run()
    verdicts += bench_batch.run()
    verdicts += bench_gradient.run()
    verdicts += bench_sympy.run()
    print_verdicts(verdicts)
    print(f"\ntotal wall time {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
