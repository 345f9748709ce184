"""Saving at ``ts`` through jaxlag's `SaveTimes` (no host callback: the program can be cached on
disk) against diffrax's ``SaveAt(ts=ts)`` (run-time checks of ``ts`` compiled in as host
callbacks), same process, alternating, one pinned core: compiled run time of ``jl.simulate`` and
of its ``jax.grad`` for the README example (particle on a sphere) with T save times.

    python -m benchmarks.bench_save_times [T ...]      # default: 2 201 2001

The diffrax route is reached by making simulate's own check of "save times it has checked"
answer no (a benchmark-only patch of a private function): everything else is the same program.
"""

import os
import sys
import time

os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jaxlag as jl  # noqa: E402
import jaxlag._simulate as simulate_module  # noqa: E402


def lagrangian(q, qd, args):
    r, th = q
    rd, thd = qd
    return 0.5 * args["m"] * (rd**2 + r**2 * thd**2) - args["m"] * args["g"] * r * jnp.cos(th)


SYSTEM = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]))
ARGS = {"m": 1.0, "g": 9.81, "R": 2.0}


def contenders(count: int) -> dict:
    ts = jnp.linspace(0.0, 2.0, count)

    def run(th):
        return jl.simulate(SYSTEM, jnp.array([2.0, th]), jnp.zeros(2), ts, args=ARGS).q

    checked = simulate_module.checked_save_times
    out = {}
    for name, rule in (("diffrax SaveAt(ts)", lambda saveat: None), ("SaveTimes", checked)):
        simulate_module.checked_save_times = rule  # read when the jitted functions are traced
        forward = jax.jit(run)
        grad = jax.jit(jax.grad(lambda th: jnp.sum(run(th)[:, 1] ** 2)))
        jax.block_until_ready((forward(0.1), grad(0.1)))
        out[name] = (forward, grad)
    simulate_module.checked_save_times = checked
    return out


def main(counts) -> None:
    print("| T | call | diffrax SaveAt(ts) ms | SaveTimes ms | ratio |\n|---|---|---|---|---|")
    for count in counts:
        fns = contenders(count)
        samples = {(name, k): [] for name in fns for k in (0, 1)}
        for _ in range(int(os.environ.get("BENCH_REPEATS", "11"))):
            for name, pair in fns.items():
                for k, fn in enumerate(pair):
                    start, calls = time.perf_counter(), 0
                    while time.perf_counter() - start < 0.05:
                        jax.block_until_ready(fn(0.1))
                        calls += 1
                    samples[(name, k)].append((time.perf_counter() - start) / calls * 1e3)
        for k, call in enumerate(("simulate", "grad")):
            a, b = (float(np.median(samples[(name, k)])) for name in fns)
            print(f"| {count} | {call} | {a:.3f} | {b:.3f} | {b / a:.3f} |", flush=True)


if __name__ == "__main__":
    main([int(x) for x in sys.argv[1:]] or [2, 201, 2001])
