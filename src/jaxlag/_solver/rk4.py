"""``jl.RK4``: the classic fourth-order Runge–Kutta method as a diffrax solver."""

import diffrax
import numpy as np
from jaxtyping import PyTree

_RK4_TABLEAU = diffrax.ButcherTableau(
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.zeros(4),  # no embedded method: constant steps only
    c=np.array([0.5, 0.5, 1.0]),
)


class RK4(diffrax.AbstractERK):
    r"""The classic fourth-order Runge–Kutta method as a diffrax solver (diffrax has none).

    Four stages ``k₁ = f(t, y)``, ``k₂ = f(t + h/2, y + h k₁/2)``, ``k₃ = f(t + h/2, y + h k₂/2)``,
    ``k₄ = f(t + h, y + h k₃)``, ``y₁ = y + h (k₁ + 2k₂ + 2k₃ + k₄)/6``; no error estimate: use
    it with ``diffrax.ConstantStepSize()``. Dense output between steps is the cubic Hermite
    interpolant of ``(y, k₁)`` and ``(y₁, f(t + h, y₁))``. Usable with ``jl.simulate`` (diffrax
    runs it) and with the ensemble integrator (which reads ``tableau``).
    """

    tableau = _RK4_TABLEAU
    interpolation_cls = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms: PyTree[diffrax.AbstractTerm]) -> int:
        del terms
        return 4
