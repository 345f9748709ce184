"""Gradient cost: one gradient of a trajectory loss divided by one forward simulation.

Double pendulum with unit masses and three parameters ``θ = (g, l₁, l₂)``,
``L = ½l₁²θ̇₁² + ½(l₁²θ̇₁² + l₂²θ̇₂² + 2l₁l₂θ̇₁θ̇₂cos(θ₁ − θ₂)) + g(2l₁cos θ₁ + l₂cos θ₂)``.
The loss is a least-squares misfit to a reference trajectory saved at 41 times in [0, 2]:
``ℓ(θ) = Σᵢ |q(tᵢ; θ) − q_data(tᵢ)|²``, evaluated away from the optimum.

Contenders (each compiled ahead of time, timed alternately):

* forward: ``ℓ(θ)``;
* reverse: ``jax.grad(ℓ)`` through diffrax's ``RecursiveCheckpointAdjoint`` (diffrax's default;
  ``max_steps`` = 65536 gives ~362 checkpoints);
* forward mode: ``jax.jacfwd(ℓ)`` with ``adjoint=diffrax.ForwardMode()``: 3 tangents pushed
  along the solve, no tape (what ``jl.fit`` uses for its Jacobians);
* ``jax.grad(ℓ)`` with jaxlag's default adjoint ``jl.ForwardSensitivities()`` (jaxlag only):
  reverse mode for the user, forward sensitivities inside for ≤ 10 differentiated scalars
  (``jaxlag.sensitivities``).

for jaxlag with a constant step (2000 steps of 1e-3) and with an adaptive
``PIDController(rtol=1e-8, atol=1e-8)``, and at the constant step also for the explicit
hand-written equations of motion: the same ratios measured on the "speed of light" tell how much
of the cost is diffrax's and how much jaxlag's.

Targets: gradient ≤ 4× forward (issue 6) and ≤ 3× with forward mode (issue 7).

Memory: peak memory of the gradient for 10⁴ steps (t ∈ [0, 10], dt = 1e-3, 101 saves), from
XLA's buffer assignment (``jit(...).lower(...).compile().memory_analysis()``: temporaries, and
temporaries plus arguments and outputs), for both adjoints and for the forward pass.

Run: ``python -m benchmarks.bench_gradient`` from the repository root.
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp

import jaxlag as jl

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported

NSTEPS = 400 if common.QUICK else 2000
T1 = 2.0
SAVES = 41
MEMORY_STEPS = 2000 if common.QUICK else 10_000
TARGET_REVERSE = 4.0
TARGET_FORWARD_MODE = 3.0
PARAMS_TRUE = {"g": 9.81, "l1": 1.0, "l2": 0.8}
PARAMS = {"g": 9.5, "l1": 1.05, "l2": 0.75}
Q0 = (2.0, -0.5)
QD0 = (0.3, -1.1)


def lagrangian(q, qd, args):
    g, l1, l2 = args["g"], args["l1"], args["l2"]
    t1, t2 = q
    w1, w2 = qd
    kinetic = 0.5 * l1**2 * w1**2 + 0.5 * (
        l1**2 * w1**2 + l2**2 * w2**2 + 2.0 * l1 * l2 * w1 * w2 * jnp.cos(t1 - t2)
    )
    return kinetic + g * (2.0 * l1 * jnp.cos(t1) + l2 * jnp.cos(t2))


def explicit(t, y, args):
    """Closed-form θ̈ for m₁ = m₂ = 1 and lengths l₁, l₂."""
    (t1, t2), (w1, w2) = y
    g, l1, l2 = args["g"], args["l1"], args["l2"]
    delta = t1 - t2
    s, c = jnp.sin(delta), jnp.cos(delta)
    den = 3.0 - jnp.cos(2.0 * delta)
    a1 = (-3.0 * g * jnp.sin(t1) - g * jnp.sin(t1 - 2.0 * t2) - 2.0 * s * (w2**2 * l2 + w1**2 * l1 * c)) / (
        l1 * den
    )
    a2 = 2.0 * s * (2.0 * w1**2 * l1 + 2.0 * g * jnp.cos(t1) + w2**2 * l2 * c) / (l2 * den)
    return y[1], jnp.stack([a1, a2])


SYSTEM = jl.System(lagrangian)


def controllers():
    return {
        f"constant step ({NSTEPS} steps)": (diffrax.ConstantStepSize(), T1 / NSTEPS),
        "adaptive, rtol = atol = 1e-8": (diffrax.PIDController(rtol=1e-8, atol=1e-8), None),
    }


def trajectory(kind, params, ts, controller, dt0, adjoint):
    q0, qd0 = jnp.array(Q0), jnp.array(QD0)
    if kind == "jaxlag":
        return jl.simulate(
            SYSTEM, q0, qd0, ts, args=params, stepsize_controller=controller, dt0=dt0, adjoint=adjoint
        ).q
    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(explicit),
        diffrax.Tsit5(),
        ts[0],
        ts[-1],
        dt0,
        (q0, qd0),
        params,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
        adjoint=adjoint,
        max_steps=2**16,
    )
    return solution.ys[0]


def make_loss(kind, ts, controller, dt0, adjoint, data):
    def loss(params):
        return jnp.sum((trajectory(kind, params, ts, controller, dt0, adjoint) - data) ** 2)

    return loss


def contenders(kind, ts, controller, dt0):
    data = trajectory(kind, PARAMS_TRUE, ts, controller, dt0, diffrax.RecursiveCheckpointAdjoint())
    reverse = make_loss(kind, ts, controller, dt0, diffrax.RecursiveCheckpointAdjoint(), data)
    forward = make_loss(kind, ts, controller, dt0, diffrax.ForwardMode(), data)
    out = [
        (f"{kind}: forward pass", reverse),
        (f"{kind}: grad, RecursiveCheckpointAdjoint", jax.grad(reverse)),
        (f"{kind}: jacfwd, ForwardMode", jax.jacfwd(forward)),
    ]
    if kind == "jaxlag":
        by_sensitivities = make_loss(kind, ts, controller, dt0, jl.ForwardSensitivities(), data)
        out.append((f"{kind}: grad, default adjoint (jl.ForwardSensitivities)", jax.grad(by_sensitivities)))
    return out


def _params():
    return {k: jnp.asarray(v) for k, v in PARAMS.items()}


def _agreement(cs):
    grads = [jax.tree.leaves(c.compiled(*c.args)) for c in cs if "forward pass" not in c.name]
    ref = jnp.stack(grads[0])
    return max(float(jnp.max(jnp.abs(jnp.stack(g) - ref) / jnp.abs(ref))) for g in grads[1:])


def memory_rows():
    """Peak memory of forward and gradient programs for MEMORY_STEPS constant steps."""
    ts = jnp.linspace(0.0, MEMORY_STEPS * 1e-3, 101)
    controller, dt0 = diffrax.ConstantStepSize(), 1e-3
    data = trajectory("jaxlag", PARAMS_TRUE, ts, controller, dt0, diffrax.RecursiveCheckpointAdjoint())
    rows = []
    for name, fn in [
        (
            "forward pass",
            make_loss("jaxlag", ts, controller, dt0, diffrax.RecursiveCheckpointAdjoint(), data),
        ),
        (
            "grad, RecursiveCheckpointAdjoint (default, max_steps=65536)",
            jax.grad(make_loss("jaxlag", ts, controller, dt0, diffrax.RecursiveCheckpointAdjoint(), data)),
        ),
        (
            "jacfwd, ForwardMode",
            jax.jacfwd(make_loss("jaxlag", ts, controller, dt0, diffrax.ForwardMode(), data)),
        ),
        (
            "grad, default adjoint (jl.ForwardSensitivities)",
            jax.grad(make_loss("jaxlag", ts, controller, dt0, jl.ForwardSensitivities(), data)),
        ),
    ]:
        c = common.compile_contender(name, fn, _params())
        c.samples = [common._sample(c) for _ in range(3)]
        stats = c.compiled.memory_analysis()
        total = (
            stats.temp_size_in_bytes
            + stats.argument_size_in_bytes
            + stats.output_size_in_bytes
            - stats.alias_size_in_bytes
        )
        rows.append(
            [name, MEMORY_STEPS, stats.temp_size_in_bytes / 1e3, total / 1e3, c.median * 1e3, c.compile_s]
        )
    forward = rows[0][4]
    for r in rows:
        r.insert(5, r[4] / forward)
    return rows


def run():
    rows, verdicts, agreement = [], [], {}
    ts = jnp.linspace(0.0, T1, SAVES)
    for label, (controller, dt0) in controllers().items():
        # The explicit baseline once, to show how much of the ratio is diffrax's own.
        for kind in ("explicit", "jaxlag") if label.startswith("constant") else ("jaxlag",):
            cs = [
                common.compile_contender(name, fn, _params())
                for name, fn in contenders(kind, ts, controller, dt0)
            ]
            common.time_alternating(cs)
            fwd = cs[0]
            for c in cs:
                rows.append(
                    [
                        label,
                        c.name,
                        c.median * 1e3,
                        c.median / fwd.median,
                        c.compile_s,
                        100 * common.spread(c),
                    ]
                )
            agreement[f"{kind}, {label}"] = _agreement(cs)
            if kind == "jaxlag":
                verdicts.append(
                    (
                        f"gradient, {label[:8]}",
                        cs[1].name,
                        "x(fwd)",
                        cs[1].median / fwd.median,
                        TARGET_REVERSE,
                    )
                )
                verdicts.append(
                    (
                        f"gradient, {label[:8]}",
                        cs[2].name,
                        "x(fwd)",
                        cs[2].median / fwd.median,
                        TARGET_FORWARD_MODE,
                    )
                )
                verdicts.append(
                    (
                        f"gradient, {label[:8]}",
                        cs[3].name,
                        "x(fwd)",
                        cs[3].median / fwd.median,
                        TARGET_REVERSE,
                    )
                )

    common.print_table(
        f"Gradient cost: double pendulum, θ = (g, l₁, l₂), loss over {SAVES} saves in [0, {T1:g}], "
        "Tsit5; ratios vs the forward pass of the same contender",
        ["steps", "contender", "ms/call", "x(forward)", "compile s", "iqr ±%"],
        rows,
    )
    print(
        "\nreverse vs forward-mode gradients, max relative difference: "
        + ", ".join(f"{k}: {v:.1e}" for k, v in agreement.items())
    )
    mem = memory_rows()
    common.print_table(
        f"Gradient memory: jaxlag double pendulum, {MEMORY_STEPS} constant steps, 101 saves; "
        "XLA buffer assignment (memory_analysis)",
        ["program", "steps", "temp kB", "total kB", "ms/call", "x(forward)", "compile s"],
        mem,
    )
    return verdicts


if __name__ == "__main__":
    from .verdicts import print_verdicts

    print(common.environment_line())
    print_verdicts(run())
