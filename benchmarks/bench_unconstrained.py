"""Unconstrained systems: jaxlag's autodiff equations of motion vs hand-derived ones.

Every contender integrates with the same diffrax solver (Tsit5), the same constant step
(``NSTEPS`` steps of ``T / NSTEPS``), ``SaveAt(t1=True)``, compiled ahead of time; the time of
one compiled call divided by the number of steps is quoted in µs/step.

Contenders
----------
Double pendulum (unit masses and lengths, g = 9.81, absolute angles from the downward vertical):

* (a) the explicit closed-form θ̈₁, θ̈₂ in ``jax.numpy`` ("speed of light");
* (b) hand-written ``M(q)`` and right-hand side, ``jnp.linalg.solve``;
* jaxlag, ``L`` written naturally, with the default in-jit initial-state check and without it.

Planar N-link chain (absolute angles, unit masses and lengths), N = 2, 5, 10, 20:

* (b) hand-written ``M_ij = (N − max(i, j)) cos(θi − θj)`` and right-hand side, ``jnp.linalg.solve``;
* jaxlag with ``L`` from cumulative sums of the link positions (default check and without);
* jaxlag with ``L = ½ q̇ᵀM(q)q̇ − V`` and ``M(q)`` assembled explicitly (without the check).

Run: ``python -m benchmarks.bench_unconstrained`` from the repository root.
"""

from __future__ import annotations

import diffrax
import jax.numpy as jnp

import jaxlag as jl

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported

G = 9.81
T = 1.0
NSTEPS = 200 if common.QUICK else 1000
NO_INITIAL_CHECK = jl.Checks(initial_state=False)
CHAIN_SIZES = (2, 5) if common.QUICK else (2, 5, 10, 20)
TARGET_VS_B = 1.0
TARGET_VS_A = 2.0


# ----------------------------------------------------------------------------- integration
def solve_hand(acceleration, q0, qd0, nsteps=NSTEPS):
    """Integrate ``q̈ = acceleration(q, q̇)`` exactly as ``jl.simulate`` would."""

    def vector_field(t, y, args):
        q, qd = y
        return qd, acceleration(q, qd)

    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(vector_field),
        diffrax.Tsit5(),
        0.0,
        T,
        T / nsteps,
        (q0, qd0),
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=nsteps + 1,
    )
    return solution.ys[0]


def hand(acceleration):
    """``(q0, qd0) ↦ q(T)`` for a hand-written ``q̈(q, q̇)``."""
    return lambda q0, qd0: solve_hand(acceleration, q0, qd0)


def with_jaxlag(system, **kwargs):
    """``(q0, qd0) ↦ q(T)`` through ``jl.simulate``."""
    return lambda q0, qd0: solve_jaxlag(system, q0, qd0, **kwargs)


def solve_jaxlag(system, q0, qd0, nsteps=NSTEPS, **kwargs):
    return jl.simulate(
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


# ----------------------------------------------------------------------------- double pendulum
def double_pendulum_explicit(q, qd):
    """(a) Closed form for m₁ = m₂ = l₁ = l₂ = 1."""
    t1, t2 = q[0], q[1]
    w1, w2 = qd[0], qd[1]
    delta = t1 - t2
    s, c = jnp.sin(delta), jnp.cos(delta)
    den = 3.0 - jnp.cos(2.0 * delta)
    a1 = (-3.0 * G * jnp.sin(t1) - G * jnp.sin(t1 - 2.0 * t2) - 2.0 * s * (w2**2 + w1**2 * c)) / den
    a2 = 2.0 * s * (2.0 * w1**2 + 2.0 * G * jnp.cos(t1) + w2**2 * c) / den
    return jnp.stack([a1, a2])


def double_pendulum_solve(q, qd):
    """(b) ``M(q) q̈ = rhs`` by ``jnp.linalg.solve``."""
    t1, t2 = q[0], q[1]
    w1, w2 = qd[0], qd[1]
    s, c = jnp.sin(t1 - t2), jnp.cos(t1 - t2)
    mass = jnp.array([[2.0, c], [c, 1.0]])
    rhs = jnp.stack([-(w2**2) * s - 2.0 * G * jnp.sin(t1), w1**2 * s - G * jnp.sin(t2)])
    return jnp.linalg.solve(mass, rhs)


def double_pendulum_lagrangian(q, qd):
    """Textbook form: ``T = ½v₁² + ½v₂²`` with ``v₂² = θ̇₁² + θ̇₂² + 2θ̇₁θ̇₂cos(θ₁ − θ₂)``."""
    t1, t2 = q
    w1, w2 = qd
    kinetic = 0.5 * w1**2 + 0.5 * (w1**2 + w2**2 + 2.0 * w1 * w2 * jnp.cos(t1 - t2))
    potential = -G * (2.0 * jnp.cos(t1) + jnp.cos(t2))
    return kinetic - potential


# ----------------------------------------------------------------------------- N-link chain
def chain_weights(n):
    """``N − max(i, j)`` (0-based): the number of masses that link i and link j both carry."""
    i = jnp.arange(n)
    return (n - jnp.maximum(i[:, None], i[None, :])).astype(jnp.float64)


def make_chain_solve(n):
    weights = chain_weights(n)
    below = (n - jnp.arange(n)).astype(jnp.float64)

    def acceleration(q, qd):
        diff = q[:, None] - q[None, :]
        mass = weights * jnp.cos(diff)
        rhs = -(weights * jnp.sin(diff)) @ (qd**2) - G * below * jnp.sin(q)
        return jnp.linalg.solve(mass, rhs)

    return acceleration


def chain_lagrangian(q, qd):
    """Natural form: link positions by cumulative sums, velocities likewise."""
    y = -jnp.cumsum(jnp.cos(q))
    vx = jnp.cumsum(jnp.cos(q) * qd)
    vy = jnp.cumsum(jnp.sin(q) * qd)
    return 0.5 * jnp.sum(vx**2 + vy**2) - G * jnp.sum(y)


def make_chain_quadratic_lagrangian(n):
    weights = chain_weights(n)
    below = (n - jnp.arange(n)).astype(jnp.float64)

    def lagrangian(q, qd):
        mass = weights * jnp.cos(q[:, None] - q[None, :])
        return 0.5 * qd @ mass @ qd + G * jnp.sum(below * jnp.cos(q))

    return lagrangian


def chain_initial_state(n):
    i = jnp.arange(n, dtype=jnp.float64)
    return 0.6 + 0.25 * jnp.sin(1.3 * i), 0.3 * jnp.cos(0.7 * i)


# ----------------------------------------------------------------------------- driver
def _row(system, n, c, ref_b, ref_a=None, nsteps=NSTEPS):
    us = c.median / nsteps * 1e6
    return [
        system,
        n,
        c.name,
        us,
        c.median / ref_b.median,
        (c.median / ref_a.median) if ref_a is not None else float("nan"),
        c.compile_s,
        100 * common.spread(c),
    ]


def _agreement(contenders, reference):
    ref = reference.compiled(*reference.args)
    return max(common.max_abs_diff(c.compiled(*c.args), ref) for c in contenders)


def run():
    rows, verdicts = [], []

    # double pendulum
    q0 = jnp.array([2.0, -0.5])
    qd0 = jnp.array([0.3, -1.1])
    system = jl.System(double_pendulum_lagrangian)
    cs = [
        common.compile_contender(name, fn, q0, qd0)
        for name, fn in [
            ("(a) explicit formula", hand(double_pendulum_explicit)),
            ("(b) M, jnp.linalg.solve", hand(double_pendulum_solve)),
            ("jaxlag", with_jaxlag(system)),
            ("jaxlag, Checks(initial_state=False)", with_jaxlag(system, checks=NO_INITIAL_CHECK)),
        ]
    ]
    common.time_alternating(cs)
    a, b = cs[0], cs[1]
    rows += [_row("double pendulum", 2, c, b, a) for c in cs]
    err = _agreement(cs[1:], a)
    for c in cs[2:]:
        verdicts.append(("double pendulum", c.name, "x(b)", c.median / b.median, TARGET_VS_B))
        verdicts.append(("double pendulum", c.name, "x(a)", c.median / a.median, TARGET_VS_A))

    # chains
    errors = {"double pendulum": err}
    for n in CHAIN_SIZES:
        q0, qd0 = chain_initial_state(n)
        natural = jl.System(chain_lagrangian)
        quadratic = jl.System(make_chain_quadratic_lagrangian(n))
        cs = [
            common.compile_contender(name, fn, q0, qd0)
            for name, fn in [
                ("(b) M, jnp.linalg.solve", hand(make_chain_solve(n))),
                ("jaxlag, L by cumsum", with_jaxlag(natural)),
                ("jaxlag, L by cumsum, no check", with_jaxlag(natural, checks=NO_INITIAL_CHECK)),
                ("jaxlag, L = ½q̇ᵀM(q)q̇ − V, no check", with_jaxlag(quadratic, checks=NO_INITIAL_CHECK)),
            ]
        ]
        common.time_alternating(cs)
        b = cs[0]
        rows += [_row("chain", n, c, b) for c in cs]
        errors[f"chain N={n}"] = _agreement(cs[1:], b)
        for c in cs[1:3]:
            verdicts.append((f"chain N={n}", c.name, "x(b)", c.median / b.median, TARGET_VS_B))

    common.print_table(
        f"Unconstrained: Tsit5, {NSTEPS} constant steps, SaveAt(t1=True); "
        "ratios vs the hand-written baselines of the same run",
        ["system", "N", "contender", "µs/step", "x(b)", "x(a)", "compile s", "iqr ±%"],
        rows,
    )
    print(
        "\nagreement with the reference, max |Δq(T)|: "
        + ", ".join(f"{k}: {v:.1e}" for k, v in errors.items())
    )
    return verdicts


def print_verdicts(verdicts):
    print("\ntargets:")
    for system, name, kind, ratio, target in verdicts:
        status = "ok  " if ratio <= target else "MISS"
        print(f"  {status} {system:16s} {name:36s} {kind} = {ratio:5.2f} (target <= {target:.1f})")


if __name__ == "__main__":
    print(common.environment_line())
    print_verdicts(run())
