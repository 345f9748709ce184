"""Small dense linear algebra for the hot path, chosen by (static) size.

For the tiny symmetric positive definite systems of mechanics (mass matrices, Schur complements
``J M⁻¹ Jᵀ``) the cost of a LAPACK custom call dominates the whole right-hand side. Up to
``UNROLL_MAX`` unknowns the Cholesky factorization and both triangular solves are written out
as scalar operations at trace time, which XLA fuses into a single kernel; above it we call
LAPACK's Cholesky (``jax.scipy.linalg.cho_factor``/``cho_solve``). Both are differentiable.
"""

from collections.abc import Callable
from typing import Any

import jax.numpy as jnp
import jax.scipy.linalg as jsl

#: Largest size for which the factorization is written out. Measured in ``benchmarks/``: the
#: written-out Cholesky beats LAPACK up to n = 8 (0.58 vs 0.77 µs) and loses from n = 9 on
#: (1.71 vs 0.88 µs), also compiling much more slowly.
UNROLL_MAX = 8


def _unrolled_cholesky(a):
    """Lower Cholesky factor (as nested lists of scalars) and reciprocal diagonal."""
    n = a.shape[0]
    lower: list[list[Any]] = [[None] * n for _ in range(n)]
    inv_diag: list[Any] = [None] * n
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s = s - lower[j][k] * lower[j][k]
        d = jnp.sqrt(s)
        inv_diag[j] = 1.0 / d
        lower[j][j] = d
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s = s - lower[i][k] * lower[j][k]
            lower[i][j] = s * inv_diag[j]
    return lower, inv_diag


def _unrolled_triangular_solves(factor, b):
    lower, inv_diag = factor
    n = len(inv_diag)
    y: list[Any] = [None] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - lower[i][k] * y[k]
        y[i] = s * inv_diag[i]
    x: list[Any] = [None] * n
    for i in reversed(range(n)):
        s = y[i]
        for k in range(i + 1, n):
            s = s - lower[k][i] * x[k]
        x[i] = s * inv_diag[i]
    return jnp.stack(x)


def spd_solver(a, diagonal: bool = False):
    """Factor a symmetric positive definite ``a`` (n, n) once; return ``solve(b)``.

    ``solve`` takes ``b`` of shape (n,) or (n, k). The factorization is written out for
    ``n <= UNROLL_MAX``, delegated to LAPACK above, and skipped when ``a`` is declared
    ``diagonal`` (then ``x = b / diag(a)``). A matrix that is not positive definite gives
    non-finite values; callers check definiteness where it can first go wrong.
    """
    n = a.shape[0]
    solve_matrix: Callable[[Any], Any]
    if diagonal:
        inverse = 1.0 / jnp.diagonal(a)
        solve_matrix = lambda rhs: inverse[:, None] * rhs
    elif n == 0:
        solve_matrix = lambda rhs: rhs
    elif n <= UNROLL_MAX:
        factor = _unrolled_cholesky(a)
        solve_matrix = lambda rhs: _unrolled_triangular_solves(factor, rhs)
    else:
        factor = jsl.cho_factor(a, lower=True)
        solve_matrix = lambda rhs: jsl.cho_solve(factor, rhs)

    def solve(b):
        if b.ndim == 1:
            return solve_matrix(b[:, None])[:, 0]
        return solve_matrix(b)

    return solve


def solve_spd(a, b, diagonal: bool = False):
    """Solve ``a x = b`` for a symmetric positive definite ``a`` (see `spd_solver`)."""
    return spd_solver(a, diagonal)(b)


def solve_psd_least_squares(a, b, rcond: float = 1e-10):
    """Minimum-norm least-squares solution of ``a x = b`` for symmetric positive semidefinite ``a``.

    Eigenvalues below ``rcond * max(eigenvalue)`` are treated as zero (``x = a⁺ b``). Used for
    redundant constraints, where ``J M⁻¹ Jᵀ`` is singular but the motion is still determined.
    """
    vector = b.ndim == 1
    rhs = b[:, None] if vector else b
    w, v = jnp.linalg.eigh(a)
    cutoff = rcond * jnp.max(jnp.abs(w))
    keep = w > cutoff
    inv_w = jnp.where(keep, 1.0 / jnp.where(keep, w, 1.0), 0.0)
    x = v @ (inv_w[:, None] * (v.T @ rhs))
    return x[:, 0] if vector else x
