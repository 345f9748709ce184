"""Batch throughput: state-steps per second of a vmapped batch of double pendulums.

B independent double pendulums (unit masses and lengths, g = 9.81, absolute angles), each
integrated with Tsit5 at a constant step, ``SaveAt(t1=True)``; one compiled call integrates the
whole batch. Throughput is ``B × steps / (time of one call)`` in state-steps per second.

Contenders, for B = 1, 64, 1024, 8192 (fewer steps for larger B, so every call is ~0.1 s):

* (a) the explicit closed-form θ̈₁, θ̈₂ (``bench_unconstrained.double_pendulum_explicit``),
  ``jax.vmap`` of ``diffrax.diffeqsolve``: the speed of light;
* jaxlag ``simulate_batch`` with the textbook ``L``, with the default initial-state check
  compiled in (once per call, vectorized over the batch) and without it.

Target: jaxlag ≤ 2× the explicit formula per step at every B (issue 7).

Run: ``python -m benchmarks.bench_batch`` from the repository root.
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp

import jaxlag as jl
from jaxlag import simulate_batch

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported
from .bench_unconstrained import T, double_pendulum_explicit, double_pendulum_lagrangian, solve_hand

#: (B, steps per call): about 1e5–2e5 state-steps per call above B = 1.
SIZES = (
    ((1, 200), (64, 100), (1024, 20)) if common.QUICK else ((1, 1000), (64, 1000), (1024, 100), (8192, 25))
)
TARGET_VS_A = 2.0


def initial_states(batch):
    """A spread of moderate-energy states (no member is special)."""
    s = jnp.linspace(0.0, 1.0, batch)
    q0 = jnp.stack([2.0 - 1.5 * s, -0.5 + 1.0 * jnp.sin(7.0 * s)], axis=1)
    qd0 = jnp.stack([0.3 * jnp.cos(5.0 * s), -1.1 + 0.5 * s], axis=1)
    return q0, qd0


def explicit_batch(nsteps):
    return jax.vmap(lambda q0, qd0: solve_hand(double_pendulum_explicit, q0, qd0, nsteps))


def jaxlag_batch(system, nsteps, **kwargs):
    def run(q0, qd0):
        return simulate_batch(
            system,
            q0,
            qd0,
            t0=0.0,
            t1=T,
            dt0=T / nsteps,
            saveat=diffrax.SaveAt(t1=True),
            solver=diffrax.Tsit5(),
            stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=nsteps + 1,
            **kwargs,
        ).q

    return run


def run():
    system = jl.System(double_pendulum_lagrangian)
    rows, verdicts, errors = [], [], {}
    for batch, nsteps in SIZES:
        q0, qd0 = initial_states(batch)
        cs = [
            common.compile_contender(name, fn, q0, qd0)
            for name, fn in [
                ("(a) explicit formula, vmap", explicit_batch(nsteps)),
                ("jaxlag simulate_batch", jaxlag_batch(system, nsteps)),
                (
                    "jaxlag simulate_batch, no check",
                    jaxlag_batch(system, nsteps, checks=jl.Checks(initial_state=False)),
                ),
            ]
        ]
        # Large batches: fewer rounds (each call already lasts ~0.1 s).
        common.time_alternating(cs, repeats=common.REPEATS if batch <= 64 else max(3, common.REPEATS // 2))
        a = cs[0]
        ref = a.compiled(*a.args)
        errors[batch] = max(common.max_abs_diff(c.compiled(*c.args), ref) for c in cs[1:])
        for c in cs:
            rate = batch * nsteps / c.median
            rows.append(
                [
                    "double pendulum",
                    batch,
                    nsteps,
                    c.name,
                    rate / 1e6,
                    c.median / (batch * nsteps) * 1e9,
                    c.median / a.median,
                    c.compile_s,
                    100 * common.spread(c),
                ]
            )
        for c in cs[1:]:
            verdicts.append((f"batch B={batch}", c.name, "x(a)", c.median / a.median, TARGET_VS_A))

    common.print_table(
        "Batch throughput: double pendulum, Tsit5, constant steps, one compiled call per batch; "
        "ratios vs the explicit formula of the same run",
        [
            "system",
            "B",
            "steps",
            "contender",
            "M state-steps/s",
            "ns/state-step",
            "x(a)",
            "compile s",
            "iqr ±%",
        ],
        rows,
    )
    print(
        "\nagreement with (a), max |Δq(T)| over the batch: "
        + ", ".join(f"B={k}: {v:.1e}" for k, v in errors.items())
    )
    return verdicts


if __name__ == "__main__":
    from .verdicts import print_verdicts

    print(common.environment_line())
    print_verdicts(run())
