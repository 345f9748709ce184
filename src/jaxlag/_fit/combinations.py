r"""The combinations of parameters that the data determine when the parameters themselves are not.

When the residuals are flat along some directions of the parameters (only ``g/l`` enters the
motion of a pendulum observed through ``θ``), the parameters along them have infinite standard
errors, but some combinations of them are determined. In log-parameter space,
``d log θ_j = dθ_j / θ_j``, a flat direction ``n`` (a row of the null space, in physical units)
becomes ``n_j / θ_j``, and every exponent vector ``a`` orthogonal to all of them gives a monomial

    c = Π_j θ_j^{a_j},    d log c = Σ_j a_j d log θ_j,

whose value does not change along the flat directions: it is determined. A basis of these
``a`` (over the parameters involved in a flat direction) is the orthogonal complement of the
null directions, written in reduced row echelon form, so that each combination leads with one
parameter to the power 1 (``g^1 · l^-1``); exponents within ``1e-4`` of a fraction with a
denominator up to 6 are rounded to it (a structural degeneracy has rational exponents; the null
directions come from a Jacobian integrated at the solver's tolerance).

Standard error by the delta method: with the gradient ``w = ∂ log c/∂θ = a/θ`` (orthogonal to
the flat directions), ``Var(log c) = wᵀ G w``, where ``G`` is the rank-revealing generalized
inverse ``σ² (JᵀJ)⁺`` (the same for every generalized inverse, since ``w`` lies in the row space
of ``J``), and ``SE(c) = |c| √Var(log c)``.
"""

from fractions import Fraction

import equinox as eqx
import numpy as np


class IdentifiableCombination(eqx.Module):
    """A combination ``θ₁^a₁ · θ₂^a₂ ⋯`` of parameters that the data determine although the
    parameters in it are not (see `FitResult.identifiable`).

    - ``name``: readable, e.g. ``"g^1 · l^-1"``;
    - ``exponents``: ``{name of the parameter: its exponent a_j}``;
    - ``value``: ``Π θ_j^{a_j}`` at the fitted parameters;
    - ``standard_error``: its standard error (delta method on ``log c``).
    """

    name: str
    exponents: dict[str, float]
    value: float
    standard_error: float


def _reduced_row_echelon(rows: np.ndarray) -> np.ndarray:
    """``rows`` (linearly independent) in reduced row echelon form, with partial pivoting."""
    a = rows.astype(float).copy()
    pivot_row = 0
    for column in range(a.shape[1]):
        if pivot_row == a.shape[0]:
            break
        best = pivot_row + int(np.argmax(np.abs(a[pivot_row:, column])))
        if abs(a[best, column]) < 1e-8:
            continue
        a[[pivot_row, best]] = a[[best, pivot_row]]
        a[pivot_row] /= a[pivot_row, column]
        for other in range(a.shape[0]):
            if other != pivot_row:
                a[other] -= a[other, column] * a[pivot_row]
        pivot_row += 1
    return a


def _rounded(exponent: float) -> float:
    fraction = Fraction(exponent).limit_denominator(6)
    return float(fraction) if abs(exponent - float(fraction)) < 1e-4 else exponent


def _power(exponent: float) -> str:
    fraction = Fraction(exponent).limit_denominator(6)
    if float(fraction) == exponent:
        return str(fraction)
    return f"{exponent:.3g}"


def identifiable_combinations(null, x, generalized, names) -> tuple[IdentifiableCombination, ...]:
    """The determined monomials of the parameters involved in the flat directions ``null``
    (rows, physical units; see `rank_revealing`), at the fitted values ``x``, with the
    generalized-inverse covariance ``generalized``; none when a parameter involved is 0 (no
    logarithm) or no combination is determined."""
    if null.shape[0] == 0:
        return ()
    involved = np.flatnonzero(np.linalg.norm(null, axis=0) > 1e-6 * np.abs(null).max())
    if involved.size == 0 or np.any(x[involved] == 0):
        return ()
    in_log = null[:, involved] / x[involved]  # the flat directions in d log|θ|
    _, s, vt = np.linalg.svd(in_log, full_matrices=True)
    rank = int(np.sum(s > 1e-8 * s[0]))
    if rank == involved.size:
        return ()
    combinations = []
    for row in _reduced_row_echelon(vt[rank:]):
        a = np.array([_rounded(v) for v in row])
        a[np.abs(a) < 1e-8] = 0.0
        values = x[involved]
        if np.any((values < 0) & (a != np.round(a))):
            continue  # a negative parameter to a fractional power: no real monomial
        sign = (-1.0) ** int(np.sum(a[values < 0]))  # integer powers there (checked above)
        value = float(sign * np.prod(np.abs(values) ** a))
        w = np.zeros(x.size)
        w[involved] = a / values
        variance = float(w @ generalized @ w)
        nonzero = np.flatnonzero(a)
        combinations.append(
            IdentifiableCombination(
                name=" · ".join(f"{names[involved[j]]}^{_power(a[j])}" for j in nonzero),
                exponents={names[involved[j]]: float(a[j]) for j in nonzero},
                value=value,
                standard_error=abs(value) * float(np.sqrt(max(variance, 0.0))),
            )
        )
    return tuple(combinations)
