"""A particle in a field: the Kepler problem, a charged particle in uniform E and B fields."""

import jax.numpy as jnp

from .._system import System
from ._common import check_form, model, parameters


@model({"m": 1.0, "k": 1.0})
def kepler(form: str = "polar") -> System:
    r"""A particle of (reduced) mass ``m`` attracted to the origin with potential ``V = −k/r``.

    - ``form="polar"``: ``q = (r, φ)``, ``L = ½ m (ṙ² + r² φ̇²) + k/r``; φ is cyclic
      (``p_φ = m r² φ̇``, the angular momentum).
    - ``form="cartesian"``: ``q = (x, y)``, ``L = ½ m |ẋ|² + k/|x|``.

    Bound orbits are ellipses of semi-major axis ``a = −k/(2E)`` and period
    ``T = 2π √(m a³/k)``; the Laplace–Runge–Lenz vector is conserved too.
    Parameters: ``m``, ``k``.
    """
    check_form("kepler", form, ("polar", "cartesian"))

    def p_of(args):
        return parameters(kepler, args)

    if form == "polar":

        def lagrangian(q, qd, args):
            p = p_of(args)
            r = q[0]
            return 0.5 * p["m"] * (qd[0] ** 2 + r**2 * qd[1] ** 2) + p["k"] / r

        return System(lagrangian)

    def lagrangian_c(q, qd, args):
        p = p_of(args)
        return 0.5 * p["m"] * jnp.sum(qd**2) + p["k"] / jnp.linalg.norm(q)

    return System(lagrangian_c)


@model({"m": 1.0, "charge": 1.0, "B": (0.0, 0.0, 1.0), "E": (0.0, 0.0, 0.0)})
def charged_particle() -> System:
    r"""A particle of mass ``m`` and charge ``charge`` in uniform fields ``E`` and ``B`` (3-vectors).

    ``q = (x, y, z)``; velocity-dependent (Lorentz) potential with the symmetric gauge
    ``A = ½ B × x``, ``ϕ = −E·x``:

        L = ½ m |ẋ|² + e ẋ·A(x) − e ϕ(x),     m ẍ = e (E + ẋ × B).

    Motion: gyration at the cyclotron frequency ``ω_c = e|B|/m`` plus the drift
    ``E × B / |B|²``. The canonical momentum along ``B`` and, for ``E = 0``, the canonical
    angular momentum about ``B`` are Noether charges. Parameters: ``m``, ``charge``, ``B``, ``E``.
    """

    def lagrangian(q, qd, args):
        p = parameters(charged_particle, args)
        b = jnp.asarray(p["B"], q.dtype)
        e_field = jnp.asarray(p["E"], q.dtype)
        potential = 0.5 * jnp.cross(b, q)
        return 0.5 * p["m"] * jnp.sum(qd**2) + p["charge"] * (jnp.dot(qd, potential) + jnp.dot(e_field, q))

    return System(lagrangian)
