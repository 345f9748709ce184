"""Compile time per N: tracing plus XLA compilation of one ``jl.simulate`` program, from cold.

The same contenders as the timing tables (Tsit5, constant steps, ``SaveAt(t1=True)``, default
initial-state check compiled in), each built from *fresh* Python functions so that no cache of
an earlier section is hit: ``trace s`` is ``jax.jit(f).lower(...)`` (tracing jaxlag and diffrax),
``XLA s`` is ``.compile()``.

* planar N-link chain, absolute angles, ``L`` by cumulative sums (unconstrained);
* Cartesian N-link chain (2N coordinates, N distance constraints) with the default
  ``Projection()`` and with ``projection=None``.

Target (issue 7): the 20-link Cartesian chain compiles in under 5 s on the 2-core machine.

Run: ``python -m benchmarks.bench_compile`` from the repository root.
"""

from __future__ import annotations

import time

import jax

import jaxlag as jl

from . import (
    bench_constrained,
    bench_unconstrained,
    common,  # first: pins the core and sets XLA_FLAGS before jax is imported
)
from .bench_unconstrained import with_jaxlag

SIZES = (2, 5) if common.QUICK else (2, 5, 10, 20)
TARGET_S = 5.0


def fresh_chain_lagrangian():
    def lagrangian(q, qd):
        return bench_unconstrained.chain_lagrangian(q, qd)

    return lagrangian


def fresh_cartesian():
    def lagrangian(q, qd):
        return bench_constrained.lagrangian(q, qd)

    def constraints(q):
        return bench_constrained.distance_constraints(q)

    return lagrangian, constraints


def cold_compile(fn, *args):
    start = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    traced = time.perf_counter()
    lowered.compile()
    done = time.perf_counter()
    return traced - start, done - traced


def run():
    rows, verdicts = [], []
    for n in SIZES:
        cases = [
            (
                "chain (angles)",
                n,
                "jaxlag, L by cumsum",
                with_jaxlag(jl.System(fresh_chain_lagrangian())),
                bench_unconstrained.chain_initial_state(n),
            ),
        ]
        for name, kwargs in [
            ("jaxlag, default Projection()", {}),
            ("jaxlag, projection=None", {"projection": None}),
        ]:
            lagrangian, constraints = fresh_cartesian()
            cases.append(
                (
                    "Cartesian chain",
                    2 * n,
                    name,
                    with_jaxlag(jl.System(lagrangian, holonomic=constraints), **kwargs),
                    bench_constrained.initial_state(n),
                )
            )
        for system, dof, name, fn, (q0, qd0) in cases:
            trace_s, xla_s = cold_compile(fn, q0, qd0)
            rows.append([system, n, dof, name, trace_s, xla_s, trace_s + xla_s])
            if system == "Cartesian chain" and n == max(SIZES) and "default" in name:
                verdicts.append(
                    (f"compile N={n}", f"Cartesian chain, {name}", "seconds", trace_s + xla_s, TARGET_S)
                )
    common.print_table(
        "Compile time from cold (fresh functions): Tsit5, constant steps, SaveAt(t1=True), "
        "default initial-state check",
        ["system", "N", "n", "contender", "trace s", "XLA s", "total s"],
        rows,
    )
    return verdicts


if __name__ == "__main__":
    from .verdicts import print_verdicts

    print(common.environment_line())
    print_verdicts(run())
