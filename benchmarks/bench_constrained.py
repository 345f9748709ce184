"""Constrained systems: jaxlag's KKT pipeline vs a hand-written KKT right-hand side.

A planar N-link chain of unit point masses in Cartesian coordinates, ``q = (x₁, y₁, …, x_N, y_N)``
(2N coordinates), ``L = ½|q̇|² − g Σ yᵢ``, with N distance constraints
``fᵢ = |pᵢ − pᵢ₋₁|² − 1 = 0`` (``p₀ = 0`` the fixed pivot). Index-1 form
``M q̈ = F + Jᵀλ``, ``J q̈ = −γ`` with ``M = I``, ``F = (0, −g, …)``, ``γᵢ = 2|vᵢ − vᵢ₋₁|²``.

Contenders (same Tsit5, same constant steps, ``SaveAt(t1=True)``, compiled ahead of time):

* hand KKT, augmented LU: the (2N + N) saddle-point matrix ``[[M, −Jᵀ], [J, 0]]`` assembled by
  hand and solved by ``jnp.linalg.solve`` (general LU);
* hand Schur: ``M = I`` used by hand, ``(J Jᵀ) λ = −γ − J F`` by ``jnp.linalg.solve`` (N × N),
  ``q̈ = F + Jᵀλ``: the reference for the ratios (the faster and the more natural hand code);
* jaxlag ``System(L, holonomic=f)`` with ``projection=None`` (the same index-1 vector field),
  with and without the in-jit initial-state check;
* jaxlag with the default ``Projection()`` after every step (extra work the baselines do not do),
* both again with ``diagonal_mass=True`` (the structure the hand-written Schur baseline exploits);
* jaxlag with the masses in ``args``: ``M`` is then inverted once per call (a dense ``M⁻¹``
  product per evaluation) rather than found constant while tracing.

jaxlag finds this ``M`` state-independent while tracing (``jaxlag.constant_mass``), so the
general ``System(L, f)`` and the one declaring ``diagonal_mass=True`` run the same code.

Run: ``python -m benchmarks.bench_constrained`` from the repository root.
"""

from __future__ import annotations

import jax.numpy as jnp

import jaxlag as jl

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported
from .bench_unconstrained import NSTEPS, hand, with_jaxlag

G = 9.81
SIZES = (2, 5) if common.QUICK else (2, 5, 10, 20)
TARGET = 1.3


def lagrangian(q, qd):
    return 0.5 * jnp.sum(qd**2) - G * jnp.sum(q[1::2])


def lagrangian_with_masses(q, qd, args):
    """The same chain with the masses as parameters (all 1 here): ``M`` depends on ``args``."""
    m = jnp.repeat(args, 2)
    return 0.5 * jnp.sum(m * qd**2) - G * jnp.sum(args * q[1::2])


def links(q):
    """Link vectors ``pᵢ − pᵢ₋₁``, shape (N, 2)."""
    p = q.reshape(-1, 2)
    return p - jnp.concatenate([jnp.zeros((1, 2), p.dtype), p[:-1]])


def distance_constraints(q):
    return jnp.sum(links(q) ** 2, axis=1) - 1.0


def _hand_terms(q, qd):
    n = q.shape[0] // 2
    d = links(q)
    dv = links(qd)
    # J[i] has 2dᵢ at link i's end point and −2dᵢ at its start point.
    eye = jnp.eye(n, dtype=q.dtype)
    below = jnp.eye(n, k=-1, dtype=q.dtype)
    jac = (2.0 * (eye - below)[:, :, None] * d[:, None, :]).reshape(n, 2 * n)
    gamma = 2.0 * jnp.sum(dv**2, axis=1)
    force = jnp.tile(jnp.array([0.0, -G], q.dtype), n)
    return jac, gamma, force


def hand_augmented(q, qd):
    jac, gamma, force = _hand_terms(q, qd)
    n2, n = q.shape[0], jac.shape[0]
    kkt = jnp.block([[jnp.eye(n2, dtype=q.dtype), -jac.T], [jac, jnp.zeros((n, n), q.dtype)]])
    return jnp.linalg.solve(kkt, jnp.concatenate([force, -gamma]))[:n2]


def hand_schur(q, qd):
    jac, gamma, force = _hand_terms(q, qd)
    lam = jnp.linalg.solve(jac @ jac.T, -gamma - jac @ force)
    return force + jac.T @ lam


def initial_state(n):
    i = jnp.arange(n, dtype=jnp.float64)
    theta = 0.6 + 0.25 * jnp.sin(1.3 * i)
    omega = 0.3 * jnp.cos(0.7 * i)
    d = jnp.stack([jnp.sin(theta), -jnp.cos(theta)], axis=1)
    w = omega[:, None] * jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=1)
    return jnp.cumsum(d, axis=0).reshape(-1), jnp.cumsum(w, axis=0).reshape(-1)


def run():
    rows, verdicts, errors, drift = [], [], {}, {}
    system = jl.System(lagrangian, holonomic=distance_constraints)
    # The hand baselines divide by the (diagonal) mass; jaxlag is told the same structure here.
    diagonal = jl.System(lagrangian, holonomic=distance_constraints, diagonal_mass=True)
    massive = jl.System(lagrangian_with_masses, holonomic=distance_constraints)
    for n in SIZES:
        q0, qd0 = initial_state(n)
        cs = [
            common.compile_contender(name, fn, q0, qd0)
            for name, fn in [
                ("hand KKT, augmented LU", hand(hand_augmented)),
                ("hand Schur (reference)", hand(hand_schur)),
                ("jaxlag, projection=None", with_jaxlag(system, projection=None)),
                (
                    "jaxlag, projection=None, no check",
                    with_jaxlag(system, projection=None, checks=jl.Checks(initial_state=False)),
                ),
                ("jaxlag, default Projection()", with_jaxlag(system)),
                ("jaxlag diagonal_mass, projection=None", with_jaxlag(diagonal, projection=None)),
                ("jaxlag diagonal_mass, default Projection()", with_jaxlag(diagonal)),
                (
                    "jaxlag, masses in args, projection=None",
                    with_jaxlag(massive, projection=None, args=jnp.ones(n)),
                ),
            ]
        ]
        common.time_alternating(cs)
        lu, ref = cs[0], cs[1]
        for c in cs:
            rows.append(
                [
                    "Cartesian chain",
                    n,
                    2 * n,
                    c.name,
                    c.median / NSTEPS * 1e6,
                    c.median / ref.median,
                    c.median / lu.median,
                    c.compile_s,
                    100 * common.spread(c),
                ]
            )
        q_ref = ref.compiled(*ref.args)
        errors[n] = max(
            common.max_abs_diff(c.compiled(*c.args), q_ref) for c in (cs[0], cs[2], cs[3], cs[5], cs[7])
        )
        drift[n] = (
            float(jnp.max(jnp.abs(distance_constraints(q_ref)))),
            float(jnp.max(jnp.abs(distance_constraints(cs[4].compiled(*cs[4].args))))),
        )
        for c in (cs[2], cs[3], cs[5], cs[7]):
            verdicts.append((f"Cartesian N={n}", c.name, "x(Schur)", c.median / ref.median, TARGET))
            verdicts.append((f"Cartesian N={n}", c.name, "x(LU)", c.median / lu.median, TARGET))

    common.print_table(
        f"Constrained (index-1 KKT): Tsit5, {NSTEPS} constant steps, SaveAt(t1=True); "
        "ratios vs the hand-written baselines of the same run",
        ["system", "N", "n", "contender", "µs/step", "x(Schur)", "x(LU)", "compile s", "iqr ±%"],
        rows,
    )
    print(
        "\nagreement of index-1 contenders with hand Schur, max |Δq(T)|: "
        + ", ".join(f"N={k}: {v:.1e}" for k, v in errors.items())
    )
    print(
        "constraint drift max|f(q(T))|, index-1 vs projected: "
        + ", ".join(f"N={k}: {a:.1e} vs {b:.1e}" for k, (a, b) in drift.items())
    )
    return verdicts


if __name__ == "__main__":
    from .bench_unconstrained import print_verdicts

    print(common.environment_line())
    print_verdicts(run())
