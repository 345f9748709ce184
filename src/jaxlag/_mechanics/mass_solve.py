r"""How ``M q̈ = F + Gᵀ Λ`` is solved: checked for hand-written mechanics, robust for learned ones.

A [`System`][jaxlag.System] holds one of these options as ``mass_solve``. Both factor the mass
matrix ``M = ∂²L/∂q̇²`` (and the Schur complement ``S = G M⁻¹ Gᵀ`` of the constraint rows
``G = [J; A]``) by a Cholesky factorization ``M = L Lᵀ``; they differ in what a matrix that is
not positive definite does:

* `CheckedCholesky` (the default): it is an error. ``System`` methods and
  [`simulate`][jaxlag.simulate] check the state and raise with the numbers (eagerly) or a static
  message (compiled, ``eqx.error_if``). Right for hand-written mechanics, where an indefinite
  ``M`` is a bug.
* `RobustSolve`: it is a value. The state *fails*: accelerations and multipliers are NaN
  for it, nothing is raised, and under ``jax.vmap`` the other members are unaffected, their
  gradients included. Right for learned Lagrangians (an MLP ``L(q, q̇)`` whose Hessian in ``q̇``
  is indefinite at initialization).

Neither computes an eigen-decomposition or an SVD inside a program: the definiteness test is the
factorization's own pivots (below), so a ``jit(vmap(grad(...)))`` over thousands of states runs
no batched LAPACK eigen-solver (jaxlib 0.10's batched ``syevd``/``gesdd``/``potrf`` kernels can
deadlock the CPU thread pool). Small matrices (n ≤ 8) are factored by written-out scalar
operations, larger ones by a loop of rank-one updates (no LAPACK call either).
"""

import abc
import numbers
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._tolerances import MASS_RCOND, rcond
from .linalg import UNROLL_MAX, _unrolled_triangular_solves, spd_solver


class Factorization:
    """``b ↦ M⁻¹ b`` from a factorization of ``M``, with its outcome.

    ``ok``: a boolean scalar (``True`` for a checked solve, which does not judge). ``finite(b)``:
    the solve with the factor of a safe matrix (finite for a failed ``M`` too, its value then
    meaningless); calling the object gives ``where(ok, finite(b), nan)``. Keeping the NaN out of
    the intermediate values is what makes the backward pass of a failed member exactly zero
    instead of ``0 · NaN`` (the "double where").
    """

    def __init__(self, finite: Callable[[Any], Any], ok):
        self.finite = finite
        self.ok = ok

    def __call__(self, b):
        return nan_unless(self.ok, self.finite(b))


def nan_unless(ok, x):
    """``x`` where ``ok``, NaN elsewhere (``ok`` a scalar: the whole of ``x``)."""
    return jnp.where(ok, x, jnp.asarray(jnp.nan, x.dtype))


class AbstractMassSolve(eqx.Module):
    """How a [`System`][jaxlag.System] solves ``M q̈ = F + Jᵀλ + Aᵀμ`` (``System(mass_solve=...)``).

    Subclasses: [`CheckedCholesky`][jaxlag.CheckedCholesky] (default; an indefinite or singular ``M`` is an
    error) and [`RobustSolve`][jaxlag.RobustSolve] (it gives NaN for that state, for learned
    Lagrangians).
    """

    #: Whether states whose ``M`` is not positive definite are errors (checked and raised).
    checked: ClassVar[bool]

    @abc.abstractmethod
    def factor(self, matrix: Float[Array, "n n"], diagonal: bool = False) -> Factorization:
        """Factor a symmetric ``matrix`` (n, n) once (a division if ``diagonal``)."""


class CheckedCholesky(AbstractMassSolve):
    r"""The default ``mass_solve``: Cholesky ``M = L Lᵀ``, with checks that raise.

    ``M q̈ = F + Jᵀλ + Aᵀμ`` is solved by the Cholesky factors of ``M`` and of the Schur
    complement ``G M⁻¹ Gᵀ``. A state where ``M`` is not positive definite (or the constraints
    are redundant) is an error: ``System`` methods raise ``ValueError`` with the eigenvalues
    (concrete inputs) or a static message from inside a compiled program (``eqx.error_if``),
    and [`simulate`][jaxlag.simulate] checks the initial state. The compiled test is the
    factorization's own pivots (see `RobustSolve` for the criterion), the eager one the
    eigenvalues: ``λ_min > 10⁻¹² λ_max`` in float64.
    """

    checked: ClassVar[bool] = True

    def factor(self, matrix: Float[Array, "n n"], diagonal: bool = False) -> Factorization:
        """Factor ``M = L Lᵀ`` (a division if ``diagonal``); no judgement (``ok`` is ``True``)."""
        return Factorization(spd_solver(matrix, diagonal), jnp.asarray(True))


def _as_python_float(value: Any) -> Any:
    """A real number (``1e-9``, ``np.float32(1e-6)``, a 0-d NumPy array) as a Python float;
    anything else unchanged, for ``__check_init__`` to refuse by name."""
    if isinstance(value, (bool, np.bool_)) or value is None:
        return value
    if isinstance(value, numbers.Real) or (
        isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "iuf"
    ):
        return float(value)
    return value


class RobustSolve(AbstractMassSolve):
    r"""``mass_solve`` for learned Lagrangians: a failed state gives NaN, never an error.

    ``M`` (and the Schur complement ``S = G M⁻¹ Gᵀ``) is factored by Cholesky, ``M = L Lᵀ``,
    whose pivots ``s_j = L_jj² = M_jj − Σ_{k<j} L_jk²`` are the diagonal of the successive Schur
    complements. **A state fails** when ``M`` has a non-finite entry, when a pivot is at or
    below the floor, or when the condition estimate from the factor exceeds ``1/rtol``:

        ``s_j ≤ rtol · max_i |M_ii|``   or   ``κ̂ = max_i M_ii · trace(M⁻¹) > n/rtol``,

    with ``rtol`` 10⁻¹² in float64 (``max(10⁻¹², 100 ε)`` in other dtypes; ``rtol=None``) and
    ``trace(M⁻¹) = ‖L⁻¹‖_F²``. ``κ̂`` is the condition number ``κ = λ_max/λ_min`` within a
    factor ``n`` (``κ/n ≤ κ̂ ≤ n κ``), and a pivot at the floor means ``κ ≥ 1/rtol``
    (``λ_min ≤ s_j``, ``max_i M_ii ≤ λ_max``). So every ``M`` with ``κ ≤ 1/rtol`` passes (the
    eigenvalue test of the eager checks, ``λ_min > rtol · λ_max``), and every indefinite or
    singular ``M``, and every ``M`` with ``κ > n²/rtol``, fails. (The pivots alone would pass
    ``M = C Cᵀ`` with a small diagonal and a large off-diagonal in ``C``, singular to working
    precision.) The same test applies to ``S`` (redundant constraints fail unless the
    system has ``least_squares=True``).

    For a failed state the accelerations, multipliers and constraint forces are NaN (the whole
    vector of that state) and nothing is raised, under ``jit``, ``vmap`` and ``grad``: the
    factorization continues with the failed pivots replaced by 1 (finite, meaningless values),
    and only the result is replaced by NaN, so the gradient of a failed member is exactly zero
    and never NaN (the other members' gradients are not poisoned). Where every pivot passes the
    result is the ordinary Cholesky solve, equal to `CheckedCholesky`'s to rounding.

    Failures are counted without a host callback: ``failed = jnp.isnan(qdd).any(-1)`` for
    accelerations ``qdd`` of shape (B, n), ``failed.sum()`` members failed; mask before any
    arithmetic, e.g. ``jnp.where(failed[:, None], 0.0, qdd)``, so a loss stays finite and its
    gradient is that of the other members. [`simulate`][jaxlag.simulate] of such a state ends with
    ``FailureCode.NONFINITE`` (per member in [`simulate_batch`][jaxlag.simulate_batch]; with
    ``throw=False``) instead of an initial-state error; the other checks (non-finite state or
    parameters, constraint residuals) still raise.
    """

    checked: ClassVar[bool] = False
    rtol: float | None = eqx.field(default=None, converter=_as_python_float)

    def __check_init__(self):
        if self.rtol is not None and not (isinstance(self.rtol, float) and 0 <= self.rtol < 1):
            raise ValueError(
                f"RobustSolve(rtol=...) must be a real number in [0, 1) or None; got {self.rtol!r}."
            )

    def floor(self, dtype: np.dtype) -> float:
        """The relative pivot floor ``rtol`` for ``dtype``."""
        return rcond(MASS_RCOND, dtype) if self.rtol is None else float(self.rtol)

    def factor(self, matrix: Float[Array, "n n"], diagonal: bool = False) -> Factorization:
        """Factor ``M`` with the pivot floor; failed states give NaN (see the class)."""
        return robust_factor(matrix, self.floor(matrix.dtype), diagonal)


def robust_factor(matrix, rtol: float, diagonal: bool = False) -> Factorization:
    """The `RobustSolve` factorization of ``matrix`` with relative pivot floor ``rtol``."""
    n = matrix.shape[0]
    finite = jnp.all(jnp.isfinite(matrix))
    safe = jnp.where(jnp.isfinite(matrix), matrix, 0.0)
    if n == 0:
        return Factorization(lambda b: b, jnp.asarray(True))
    scale = jnp.max(jnp.abs(jnp.diagonal(safe)))
    floor = jax.lax.stop_gradient(rtol * scale)
    if diagonal:
        d = jnp.diagonal(safe)
        good = d > floor
        inverse = 1.0 / jnp.where(good, d, 1.0)
        ok = finite & jnp.all(good)

        def solve_diagonal(b):
            return inverse * b if b.ndim == 1 else inverse[:, None] * b

        return Factorization(solve_diagonal, ok)
    solve, pivots_ok = clipped_cholesky(safe, floor)
    return Factorization(solve, finite & pivots_ok & well_conditioned(solve, scale, rtol, n))


def well_conditioned(solve: Callable[[Any], Any], scale, rtol: float, n: int) -> Bool[Array, ""]:
    """Whether ``κ̂ = max_i M_ii · trace(M⁻¹) ≤ n/rtol``, with ``M⁻¹`` from the factor's ``solve``.

    ``κ̂`` is ``M``'s condition number within a factor ``n``: ``λ_max/n ≤ max_i M_ii ≤ λ_max``
    and ``1/λ_min ≤ trace(M⁻¹) ≤ n/λ_min``. So ``κ ≤ 1/rtol`` (the eigenvalue test of the eager
    checks) passes, ``κ > n²/rtol`` fails. The pivots alone do not bound it: ``M = C Cᵀ`` with
    ``C = [[10⁻³, 0], [30, 10⁻³]]`` has pivots ``10⁻⁶`` against ``max M_ii ≈ 900`` and
    ``κ ≈ 10¹⁵``. Costs ``n`` solves with the factor (no eigenvalues)."""
    inverse_trace = jnp.trace(jax.lax.stop_gradient(solve(jnp.eye(n, dtype=scale.dtype))))
    estimate = jax.lax.stop_gradient(scale) * inverse_trace
    return estimate <= n / rtol


def clipped_cholesky(a, floor) -> tuple[Callable[[Any], Any], Bool[Array, ""]]:
    """``(solve, ok)``: ``b ↦ (L Lᵀ)⁻¹ b`` for the lower Cholesky factor ``L`` of ``a`` with every
    pivot ``s_j ≤ floor`` replaced by 1 (so the solve is finite for any finite ``a``), and
    whether no pivot was. No LAPACK call: written out for ``n ≤ UNROLL_MAX``, loops over the
    columns above (``b`` of shape (n,) or (n, k))."""
    n = a.shape[0]
    if n <= UNROLL_MAX:
        rows: list[list[Any]] = [[None] * n for _ in range(n)]
        inv_diag: list[Any] = [None] * n
        ok = jax.device_put(True)  # a transfer, not an eager program when evaluated op by op
        for j in range(n):
            s = a[j, j]
            for k in range(j):
                s = s - rows[j][k] * rows[j][k]
            good = s > floor
            ok = ok & good
            d = jnp.sqrt(jnp.where(good, s, 1.0))
            rows[j][j] = d
            inv_diag[j] = 1.0 / d
            for i in range(j + 1, n):
                s_ij = a[i, j]
                for k in range(j):
                    s_ij = s_ij - rows[i][k] * rows[j][k]
                rows[i][j] = s_ij * inv_diag[j]

        def unrolled(b):
            rhs = b[:, None] if b.ndim == 1 else b
            x = _unrolled_triangular_solves((rows, inv_diag), rhs)
            return x[:, 0] if b.ndim == 1 else x

        return unrolled, ok
    index = jnp.arange(n)

    def column(j, carry):
        lower, ok = carry
        row = lower[j]  # entries k < j are final, the others still zero
        s = a[j, j] - row @ row
        good = s > floor
        d = jnp.sqrt(jnp.where(good, s, 1.0))
        below = (a[:, j] - lower @ row) / d
        col = jnp.where(index > j, below, jnp.where(index == j, d, 0.0))
        return lower.at[:, j].set(col), ok & good

    lower, ok = jax.lax.fori_loop(0, n, column, (jnp.zeros_like(a), jnp.asarray(True)))
    diag = jnp.diagonal(lower)

    def looped(b):
        rhs = b[:, None] if b.ndim == 1 else b

        def forward(i, y):  # L y = b, row by row (entries of y below i still zero)
            return y.at[i].set((rhs[i] - lower[i] @ y) / diag[i])

        def backward(k, x):  # Lᵀ x = y, from the last row up
            i = n - 1 - k
            return x.at[i].set((y[i] - lower[:, i] @ x) / diag[i])

        y = jax.lax.fori_loop(0, n, forward, jnp.zeros_like(rhs))
        x = jax.lax.fori_loop(0, n, backward, jnp.zeros_like(rhs))
        return x[:, 0] if b.ndim == 1 else x

    return looped, ok


def pivots_pass(a, rtol: float) -> Bool[Array, ""]:
    """Whether the symmetric ``a`` passes the `RobustSolve` test (finite, every Cholesky
    pivot above ``rtol · max_i |a_ii|``, ``max_i a_ii · trace(a⁻¹) ≤ n/rtol``): the compiled
    definiteness check, without eigenvalues."""
    if a.shape[0] == 0:
        return jnp.asarray(True)
    a = jax.lax.stop_gradient(a)
    finite = jnp.all(jnp.isfinite(a))
    safe = jnp.where(jnp.isfinite(a), a, 0.0)
    scale = jnp.max(jnp.abs(jnp.diagonal(safe)))
    solve, pivots_ok = clipped_cholesky(safe, rtol * scale)
    return finite & pivots_ok & well_conditioned(solve, scale, rtol, a.shape[0])


def independent_rows(rows, rtol: float) -> Bool[Array, ""]:
    """Whether the rows of ``rows`` (m, n) are linearly independent, without an SVD: every pivot
    of the Cholesky factorization of the Gram matrix of the normalized rows (``sin²`` of the
    angle between a row and the span of the rows before it) is above ``rtol``. Zero rows
    (inactive constraints) count as independent."""
    if rows.shape[0] == 0:
        return jnp.asarray(True)
    rows = jax.lax.stop_gradient(rows)
    norms = jnp.sqrt(jnp.sum(rows * rows, axis=1))
    live = norms > 0
    unit = rows / jnp.where(live, norms, 1.0)[:, None]
    gram = unit @ unit.T + jnp.diag(jnp.where(live, 0.0, 1.0))
    return jnp.all(jnp.isfinite(rows)) & clipped_cholesky(gram, rtol)[1]
