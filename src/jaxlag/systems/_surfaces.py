"""A particle held on a curve or a surface: hoop, rotating parabolic wire, cone, sphere, spiral.

Spatial models use (x, y, z) with z up and gravity ``−g ẑ``. Each model comes in a form with the
constraint solved by the coordinates (``"generalized"``, no multipliers) and one with the
constraint imposed by a multiplier (the multiplier is then the constraint force, signed as the
constraint function's gradient: ``M q̈ = F + Jᵀλ``).
"""

import jax.numpy as jnp

from .._system import System
from ..coordinates import cylindrical, lagrangian_from_positions, spherical
from ._common import check_form, model, parameters


@model({"m": 1.0, "R": 1.0, "g": 9.81, "omega": 0.0})
def bead_on_hoop(form: str = "generalized") -> System:
    r"""A bead of mass ``m`` on a vertical circular hoop of radius ``R`` spinning about the vertical
    diameter at the constant rate ``omega`` (0: a fixed hoop, the pendulum of the seeds).

    - ``form="generalized"``: ``q = (θ,)``, the angle from the bottom of the hoop; position
      ``R (sin θ cos ωt, sin θ sin ωt, −cos θ)`` (centre at the origin);
      ``L = ½ m R² (θ̇² + ω² sin²θ) + m g R cos θ``.
    - ``form="cartesian"``: ``q = (x, y, z)`` with ``f = (|x| − R, −x sin ωt + y cos ωt)``
      (the sphere and the rotating plane of the hoop; rheonomic when ω ≠ 0). ``λ₁`` is the
      radial (outward) constraint force.

    Equilibria: the bottom θ = 0 (stable iff ``ω² < g/R``, frequency ``√(g/R − ω²)``) and, for
    ``ω² > g/R``, ``cos θ* = g/(R ω²)`` with frequency ``ω sin θ*``.
    Parameters: ``m``, ``R``, ``g``, ``omega``.
    """
    check_form("bead_on_hoop", form, ("generalized", "cartesian"))

    def p_of(args):
        return parameters(bead_on_hoop, args)

    mass = lambda a: p_of(a)["m"]  # noqa: E731
    gravity = lambda a: p_of(a)["g"]  # noqa: E731
    if form == "generalized":

        def positions(q, t, args):
            p = p_of(args)
            return spherical(p["R"], jnp.pi - q[0], p["omega"] * t)

        return System(lagrangian_from_positions(positions, mass, gravity=gravity))

    def hoop(q, t, args):
        p = p_of(args)
        wt = p["omega"] * t
        return jnp.stack([jnp.linalg.norm(q) - p["R"], -q[0] * jnp.sin(wt) + q[1] * jnp.cos(wt)])

    return System(lagrangian_from_positions(lambda q: q, mass, gravity=gravity), holonomic=hoop)


@model({"m": 1.0, "c": 1.0, "g": 9.81, "omega": 1.0})
def bead_on_rotating_parabola(form: str = "generalized") -> System:
    r"""A bead of mass ``m`` on a wire ``z = c r²`` spinning about the vertical at the rate ``omega``
    (Thornton & Marion §7).

    - ``form="generalized"``: ``q = (r,)``, the signed distance from the axis; position
      ``(r cos ωt, r sin ωt, c r²)``; ``L = ½ m (ṙ² (1 + 4c²r²) + ω² r²) − m g c r²``:

          r̈ (1 + 4c²r²) + 4c² r ṙ² + (2gc − ω²) r = 0.

    - ``form="cylindrical"``: ``q = (r, φ, z)``, ``L = ½ m (ṙ² + r²φ̇² + ż²) − m g z`` with
      ``f = (z − c r², φ − ωt)`` (the second constraint is rheonomic: the wire drives the bead).

    ``r = 0`` is always an equilibrium, stable for ``ω² < 2gc`` (frequency ``√(2gc − ω²)``) and
    unstable for ``ω² > 2gc``; at ``ω² = 2gc`` every radius is an equilibrium.
    Parameters: ``m``, ``c``, ``g``, ``omega``.
    """
    check_form("bead_on_rotating_parabola", form, ("generalized", "cylindrical"))

    def p_of(args):
        return parameters(bead_on_rotating_parabola, args)

    mass = lambda a: p_of(a)["m"]  # noqa: E731
    gravity = lambda a: p_of(a)["g"]  # noqa: E731
    if form == "generalized":

        def rotating_positions(q, t, args):
            p = p_of(args)
            return cylindrical(q[0], p["omega"] * t, p["c"] * q[0] ** 2)

        return System(lagrangian_from_positions(rotating_positions, mass, gravity=gravity))

    def positions(q):
        return cylindrical(q[0], q[1], q[2])

    def wire(q, t, args):
        p = p_of(args)
        return jnp.stack([q[2] - p["c"] * q[0] ** 2, q[1] - p["omega"] * t])

    return System(lagrangian_from_positions(positions, mass, gravity=gravity), holonomic=wire)


@model({"m": 1.0, "g": 9.81, "alpha": 0.5})
def particle_on_cone(form: str = "generalized") -> System:
    r"""A particle of mass ``m`` sliding on the inside of a cone with its apex down at the origin,
    axis vertical, half-angle ``alpha`` (Taylor, Classical Mechanics, 7.38).

    - ``form="generalized"``: ``q = (r, φ)``, ``r`` the distance from the apex along the
      surface, φ the azimuth: ``L = ½ m (ṙ² + r² sin²α φ̇²) − m g r cos α``. φ is cyclic:
      ``l_z = m r² sin²α φ̇`` is conserved.
    - ``form="spherical"``: ``q = (r, θ, φ)`` spherical coordinates with ``f = θ − α``.
    - ``form="cartesian"``: ``q = (x, y, z)`` with ``f = √(x² + y²) cos α − z sin α`` (the
      signed distance to the surface); ``λ`` is the normal force.

    Circular orbits: ``r₀ = (l_z² / (m² g sin²α cos α))^{1/3}``, oscillating about it at
    ``Ω = √(3 g cos α / r₀)``. Parameters: ``m``, ``g``, ``alpha``.
    """
    check_form("particle_on_cone", form, ("generalized", "spherical", "cartesian"))

    def p_of(args):
        return parameters(particle_on_cone, args)

    mass = lambda a: p_of(a)["m"]  # noqa: E731
    gravity = lambda a: p_of(a)["g"]  # noqa: E731
    if form == "generalized":

        def positions(q, args):
            return spherical(q[0], p_of(args)["alpha"], q[1])

        return System(lagrangian_from_positions(positions, mass, gravity=gravity))
    if form == "spherical":

        def cone(q, args):
            return jnp.reshape(q[1] - p_of(args)["alpha"], (1,))

        return System(
            lagrangian_from_positions(lambda q: spherical(q[0], q[1], q[2]), mass, gravity=gravity),
            holonomic=cone,
        )

    def surface(q, args):
        a = p_of(args)["alpha"]
        return jnp.reshape(jnp.linalg.norm(q[:2]) * jnp.cos(a) - q[2] * jnp.sin(a), (1,))

    return System(lagrangian_from_positions(lambda q: q, mass, gravity=gravity), holonomic=surface)


@model({"m": 1.0, "R": 1.0, "g": 9.81})
def particle_on_sphere(form: str = "spherical", unilateral: bool = False) -> System:
    r"""A particle of mass ``m`` on a sphere of radius ``R`` centred at the origin.

    - ``form="spherical"``: ``q = (r, θ, φ)``, θ from the top (+z), with ``f = r − R``;
      ``L = ½ m (ṙ² + r²θ̇² + r² sin²θ φ̇²) − m g r cos θ``.
    - ``form="cartesian"``: ``q = (x, y, z)`` with ``f = |x| − R``.

    ``λ`` is the outward normal force; released from rest at θ₀ on the outside,
    ``λ = m g (3 cos θ − 2 cos θ₀)``, vanishing at ``cos θ = ⅔ cos θ₀``. With
    ``unilateral=True`` the constraint is one-sided (``f ≥ 0``, the outside) and the particle
    leaves the sphere there (see [`jaxlag.simulate`][jaxlag.simulate]). Parameters: ``m``, ``R``, ``g``.
    """
    check_form("particle_on_sphere", form, ("spherical", "cartesian"))

    def p_of(args):
        return parameters(particle_on_sphere, args)

    mass = lambda a: p_of(a)["m"]  # noqa: E731
    gravity = lambda a: p_of(a)["g"]  # noqa: E731
    one_sided = (0,) if unilateral else ()
    if form == "spherical":

        def sphere(q, args):
            return jnp.reshape(q[0] - p_of(args)["R"], (1,))

        lagrangian = lagrangian_from_positions(lambda q: spherical(q[0], q[1], q[2]), mass, gravity=gravity)
        return System(lagrangian, holonomic=sphere, unilateral=one_sided)

    def sphere_c(q, args):
        return jnp.reshape(jnp.linalg.norm(q) - p_of(args)["R"], (1,))

    return System(
        lagrangian_from_positions(lambda q: q, mass, gravity=gravity),
        holonomic=sphere_c,
        unilateral=one_sided,
    )


@model({"m": 1.0, "a": 1.0})
def spiral(form: str = "polar") -> System:
    r"""A free particle (no gravity) of mass ``m`` on the Archimedean spiral ``r = a θ`` in a plane.

    - ``form="polar"``: ``q = (r, θ)``, ``L = ½ m (ṙ² + r² θ̇²)``, ``f = r − a θ``; then
      ``θ̈ = −θ θ̇²/(1 + θ²)`` and ``λ = −m a θ̇² (2θ + θ³)/(1 + θ²)``.
    - ``form="generalized"``: ``q = (θ,)``, ``L = ½ m a² (1 + θ²) θ̇²``.

    The speed ``a |θ̇| √(1 + θ²)`` is constant. Parameters: ``m``, ``a``.
    """
    check_form("spiral", form, ("polar", "generalized"))

    def p_of(args):
        return parameters(spiral, args)

    if form == "generalized":

        def lagrangian(q, qd, args):
            p = p_of(args)
            return 0.5 * p["m"] * p["a"] ** 2 * (1.0 + q[0] ** 2) * qd[0] ** 2

        return System(lagrangian)

    def lagrangian_polar(q, qd, args):
        r, _ = q
        rd, thd = qd
        return 0.5 * p_of(args)["m"] * (rd**2 + r**2 * thd**2)

    def curve(q, args):
        return jnp.reshape(q[0] - p_of(args)["a"] * q[1], (1,))

    return System(lagrangian_polar, holonomic=curve)
