"""Run every jaxlag benchmark and print the ratio tables.

``python -m benchmarks`` (or ``python -m benchmarks.run_all``) from the repository root.
"""

from __future__ import annotations

import time

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported
from . import bench_constrained, bench_unconstrained


def main() -> None:
    start = time.perf_counter()
    print(common.environment_line())
    verdicts = bench_unconstrained.run()
    verdicts += bench_constrained.run()
    bench_unconstrained.print_verdicts(verdicts)
    print(f"\ntotal wall time {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
