r"""The constrained equations of motion as a structured KKT solve.

With stacked constraint rows ``G = [J; A]`` (holonomic and velocity constraints) the equations

    M q̈ = F + Gᵀ Λ,        G q̈ = c,

(``Λ = [λ; μ]``, sign convention of the seeds: ``d/dt ∂L/∂q̇ − ∂L/∂q = Jᵀλ + Aᵀμ + Qⁿᶜ``) form the
saddle-point system ``[[M, −Gᵀ], [G, 0]] [q̈; Λ] = [F; c]``. ``M`` is symmetric positive definite,
so it is solved in range-space (Schur complement) form, never as a general LU of the augmented
matrix:

    X = M⁻¹ [F, Gᵀ]                     (one Cholesky of M, m + 1 right-hand sides)
    S = G M⁻¹ Gᵀ,   S Λ = c − G M⁻¹F     (a second, m × m Cholesky)
    q̈ = M⁻¹F + M⁻¹Gᵀ Λ.

When the constraints are redundant ``S`` is singular; with ``least_squares=True`` on the
[`System`][jaxlag.System] ``Λ = S⁺(c − G M⁻¹F)`` is the minimum-norm choice, and ``q̈`` is still
unique when the redundant constraints are consistent.
"""

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp

from .constraints import constraint_rows
from .lagrangian import mass_solver_and_forces
from .linalg import solve_psd_least_squares, solve_spd
from .mass_solve import AbstractMassSolve, CheckedCholesky, Factorization, nan_unless


def deactivate(rows, rhs, active):
    """Zero the rows (and right-hand sides) of inactive constraints.

    Returns ``(rows, rhs, pad)`` where ``pad = diag(1 − active)`` is added to the Schur complement
    so that it stays invertible and the inactive multipliers come out exactly zero. Shapes stay
    static, so switching a unilateral constraint on or off never recompiles.
    """
    if active is None:
        return rows, rhs, None
    weight = jnp.asarray(active, rows.dtype)
    return rows * weight[:, None], rhs * weight, jnp.diag(1.0 - weight)


def solve_kkt(
    mass,
    force,
    rows,
    rhs,
    least_squares: bool = False,
    active=None,
    diagonal_mass: bool = False,
    mass_solve: AbstractMassSolve = CheckedCholesky(),
):
    """Solve ``M q̈ = F + Gᵀ Λ``, ``G q̈ = c``; return ``(q̈, Λ)``.

    ``mass`` is ``M`` (n, n), factored here (a division if ``diagonal_mass``), or a function
    ``b ↦ M⁻¹ b`` for vectors and matrices (a `Factorization`,
    `jaxlag._mechanics.linalg.spd_solver`'s result); ``active`` (m,) optionally switches
    constraints off (their multipliers are zero). ``mass_solve`` factors ``M`` and the Schur
    complement: with [`RobustSolve`][jaxlag.RobustSolve] a failed ``M`` or Schur complement makes the
    whole result NaN, computed from finite intermediate values (zero gradient, never NaN).
    """
    factored = mass if isinstance(mass, Factorization) else None
    if factored is None and not callable(mass):
        factored = mass_solve.factor(mass, diagonal_mass)
    # The finite solve: NaN enters only at the end, where ok is known (see Factorization).
    solve_mass: Callable[[Any], Any] = factored.finite if factored is not None else mass
    ok = factored.ok if factored is not None else jnp.asarray(True)
    m = rows.shape[0]
    if m == 0:
        return nan_unless(ok, solve_mass(force)), jnp.zeros((0,), force.dtype)
    rows, rhs, pad = deactivate(rows, rhs, active)
    solved = solve_mass(jnp.concatenate([force[:, None], rows.T], axis=1))
    free, minv_gt = solved[:, 0], solved[:, 1:]
    schur = rows @ minv_gt
    if pad is not None:
        schur = schur + pad
    residual = rhs - rows @ free
    if least_squares:
        multipliers = solve_psd_least_squares(schur, residual)
    elif mass_solve.checked:
        multipliers = solve_spd(schur, residual)
    else:
        schur_factor = mass_solve.factor(0.5 * (schur + schur.T))
        multipliers = schur_factor.finite(residual)
        ok = ok & schur_factor.ok
    return nan_unless(ok, free + minv_gt @ multipliers), nan_unless(ok, multipliers)


def accelerations_and_multipliers(system, q, qd, t, args, baumgarte=None, active=None):
    """``(q̈, λ, μ)`` at a state: accelerations, holonomic and velocity-constraint multipliers.

    ``active`` (m_h,) optionally marks which holonomic constraints currently act (unilateral
    constraints that have let go are inactive; their ``λ`` is zero).
    """
    solve_mass, force = mass_solver_and_forces(system, q, qd, t, args)
    rows, rhs = constraint_rows(system, q, qd, t, args, baumgarte)
    m_h = system.num_holonomic(q, t, args)
    if active is not None:
        active = jnp.concatenate([jnp.asarray(active, q.dtype), jnp.ones((rows.shape[0] - m_h,), q.dtype)])
    qdd, multipliers = solve_kkt(
        solve_mass, force, rows, rhs, system.least_squares, active, mass_solve=system.mass_solve
    )
    return qdd, multipliers[:m_h], multipliers[m_h:]
