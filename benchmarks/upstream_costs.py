"""Compile-time costs that sit in diffrax and equinox, measured for docs/compile-time.md.

1. diffrax's ``t1 − 100 ULPs`` threshold (``_integrate.py``: 100 chained
   ``equinox.internal.prevbefore`` calls in every solve program): the HLO operations it adds, and
   the XLA compile time of the chain alone, against one ``jnp.nextafter``-free loop.
2. diffrax's checks of traced save times (``eqx.error_if`` on ``saveat.ts``): a solve program
   whose save times are an input carries host callbacks, which JAX's persistent cache refuses.

    python -m benchmarks.upstream_costs
"""

from __future__ import annotations

import os
import statistics
import time

import diffrax
import equinox.internal as eqxi
import jax
import jax.numpy as jnp

try:
    os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})
except (AttributeError, OSError):
    pass
jax.config.update("jax_enable_x64", True)


def chain(t1):
    for _ in range(100):
        t1 = eqxi.prevbefore(t1)
    return t1


def loop(t1):
    return jax.lax.fori_loop(0, 100, lambda _, x: eqxi.prevbefore(x), t1)


def compile_seconds(fn, repeats=5):
    times = []
    for i in range(repeats):
        # A new constant in each program: XLA's in-process cache cannot serve a repeat.
        lowered = jax.jit(lambda t, i=i: fn(t * (1.0 + 1e-3 * i))).lower(jnp.float64(1.0))
        start = time.perf_counter()
        lowered.compile()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def ops(fn):
    return jax.jit(fn).lower(1.0).as_text().count(" = ")


def solve(ts, y0):
    term = diffrax.ODETerm(lambda t, y, args: -y)
    return diffrax.diffeqsolve(
        term,
        diffrax.Tsit5(),
        ts[0],
        ts[-1],
        None,
        y0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=1e-8, atol=1e-8),
    ).ys


def main():
    print(f"jax {jax.__version__}, diffrax {diffrax.__version__}, backend {jax.default_backend()}")
    print(
        f"100 chained prevbefore: {ops(chain)} HLO ops, XLA compile {compile_seconds(chain):.3f} s "
        f"(median of 5); as one loop: {ops(loop)} ops, {compile_seconds(loop):.3f} s"
    )
    whole = jax.jit(solve).lower(jnp.linspace(0.0, 1.0, 11), jnp.ones(2)).as_text()
    print(
        f"a plain Tsit5 solve program: {whole.count(' = ')} HLO ops, "
        f"{whole.count('next_after') + whole.count('nextafter')} nextafter ops"
    )
    callbacks = whole.count("callback")
    print(
        f"host callbacks in a solve whose save times are an input: {callbacks} "
        "(JAX's persistent cache does not store such a program)"
    )


if __name__ == "__main__":
    main()
