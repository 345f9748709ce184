"""Pendulums and chains: simple, double, N-link, spherical; a free chain; the cart-pole.

Planar models live in the vertical (x, y) plane with y up; spatial ones use (x, y, z) with z up.
Angles of planar pendulums are measured from the downward vertical (hanging at rest is 0), except
the cart-pole's, measured from the upward vertical (upright is 0).
"""

from collections.abc import Callable, Mapping

import jax.numpy as jnp

from .._conventions import wrap_state_function
from .._system import System
from ..coordinates import RigidBody2D, lagrangian_from_positions, planar_chain
from ._common import KeyReads, check_form, check_keys, model, parameters

_FORMS = ("generalized", "cartesian")


def _chain_system(factory, n: int, form: str, masses: Callable, lengths: Callable) -> System:
    """A planar chain of ``n`` point masses on massless rods hanging from the origin."""
    check_form(factory.__name__, form, _FORMS)

    def gravity(args):
        return parameters(factory, args)["g"]

    def mass_of(args):
        return masses(parameters(factory, args))

    if form == "generalized":

        def positions(q, args):
            return planar_chain(q, lengths(parameters(factory, args)))

        return System(lagrangian_from_positions(positions, mass_of, gravity=gravity))

    def points(q):
        return q.reshape(n, 2)

    def rods(q, args):
        x = points(q)
        previous = jnp.concatenate([jnp.zeros((1, 2), q.dtype), x[:-1]])
        return jnp.linalg.norm(x - previous, axis=-1) - lengths(parameters(factory, args))

    return System(lagrangian_from_positions(points, mass_of, gravity=gravity), holonomic=rods)


@model({"m": 1.0, "l": 1.0, "g": 9.81})
def simple_pendulum(form: str = "generalized") -> System:
    r"""A point mass ``m`` on a massless rod of length ``l`` under gravity ``g``.

    - ``form="generalized"``: ``q = (θ,)``, the angle from the downward vertical;
      ``L = ½ m l² θ̇² + m g l cos θ``.
    - ``form="cartesian"``: ``q = (x, y)`` (y up, pivot at the origin), ``L = ½ m |ẋ|² − m g y``
      with ``f = √(x² + y²) − l = 0``; the multiplier is minus the rod tension,
      ``λ = −m l θ̇² − m g cos θ``.

    Small oscillations: ``ω = √(g/l)``. Parameters (``args``): ``m``, ``l``, ``g``.
    """
    return _chain_system(
        simple_pendulum, 1, form, lambda p: jnp.reshape(p["m"], (1,)), lambda p: jnp.reshape(p["l"], (1,))
    )


@model({"m1": 1.0, "m2": 1.0, "l1": 1.0, "l2": 1.0, "g": 9.81})
def double_pendulum(form: str = "generalized") -> System:
    r"""Two point masses ``m1``, ``m2`` on massless rods ``l1``, ``l2`` (the second hangs from the first).

    - ``form="generalized"``: ``q = (θ₁, θ₂)``, absolute angles from the downward vertical.
    - ``form="cartesian"``: ``q = (x₁, y₁, x₂, y₂)`` (y up, pivot at the origin) with
      ``f = (|x₁| − l₁, |x₂ − x₁| − l₂)``; multipliers are minus the rod tensions.

    For ``m1 = m2``, ``l1 = l2 = l`` the normal-mode frequencies are ``ω² = (2 ∓ √2) g/l``.
    Parameters: ``m1``, ``m2``, ``l1``, ``l2``, ``g``.
    """
    return _chain_system(
        double_pendulum,
        2,
        form,
        lambda p: jnp.stack([p["m1"], p["m2"]]),
        lambda p: jnp.stack([p["l1"], p["l2"]]),
    )


@model({"m": 1.0, "l": 1.0, "g": 9.81})
def n_link_pendulum(n: int, form: str = "generalized") -> System:
    r"""A planar chain of ``n`` point masses on massless rods, hanging from the origin.

    - ``form="generalized"``: ``q = (θ₁, …, θ_n)``, absolute angles from the downward vertical.
    - ``form="cartesian"``: ``q = (x₁, y₁, …, x_n, y_n)`` with the ``n`` rod constraints
      ``f_k = |x_k − x_{k−1}| − l_k`` (``x₀`` the pivot).

    Parameters: ``m`` and ``l`` (scalars or arrays of length ``n``), ``g``.
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"n_link_pendulum needs n >= 1 links; got {n}.")
    return _chain_system(
        n_link_pendulum,
        n,
        form,
        lambda p: jnp.broadcast_to(jnp.asarray(p["m"]), (n,)),
        lambda p: jnp.broadcast_to(jnp.asarray(p["l"]), (n,)),
    )


@model({"m": 1.0, "l": 1.0, "g": 9.81})
def spherical_pendulum(form: str = "generalized") -> System:
    r"""A point mass ``m`` on a massless rod of length ``l`` free to swing in 3-D (z up).

    - ``form="generalized"``: ``q = (θ, φ)``, θ the angle from the downward vertical, φ the
      azimuth: position ``l (sin θ cos φ, sin θ sin φ, −cos θ)``;
      ``L = ½ m l² (θ̇² + sin²θ φ̇²) + m g l cos θ``. φ is cyclic: ``p_φ = L_z`` is conserved.
      (The coordinates are singular at θ = 0: use the Cartesian form through the bottom.)
    - ``form="cartesian"``: ``q = (x, y, z)``, ``f = |x| − l``; rotations about z are a symmetry
      with charge ``L_z = m (x ẏ − y ẋ)``.

    Parameters: ``m``, ``l``, ``g``.
    """
    check_form("spherical_pendulum", form, _FORMS)

    def p_of(args):
        return parameters(spherical_pendulum, args)

    if form == "generalized":

        def positions(q, args):
            th, ph = q
            s = jnp.sin(th)
            return p_of(args)["l"] * jnp.stack([s * jnp.cos(ph), s * jnp.sin(ph), -jnp.cos(th)])

        return System(
            lagrangian_from_positions(positions, lambda a: p_of(a)["m"], gravity=lambda a: p_of(a)["g"])
        )

    def rod(q, args):
        return jnp.reshape(jnp.linalg.norm(q) - p_of(args)["l"], (1,))

    return System(
        lagrangian_from_positions(lambda q: q, lambda a: p_of(a)["m"], gravity=lambda a: p_of(a)["g"]),
        holonomic=rod,
    )


@model({"m": 1.0, "l": 1.0, "g": 0.0})
def free_chain(n: int, dim: int = 2) -> System:
    r"""``n`` point masses joined in a row by ``n − 1`` rigid massless links, free in space.

    ``q = (x₁, …, x_n)`` flattened, each ``x_k`` in ``dim`` dimensions (last axis up);
    ``L = ½ m Σ|ẋ_k|² − m g Σ x_k[-1]``, ``f_k = |x_{k+1} − x_k| − l``. Translations are a
    symmetry (the horizontal ones also with gravity): total linear momentum is the Noether charge.
    Parameters: ``m`` (scalar or ``(n,)``), ``l`` (scalar or ``(n−1,)``), ``g`` (default 0).
    """
    n, dim = int(n), int(dim)
    if n < 2 or dim not in (2, 3):
        raise ValueError(f"free_chain needs n >= 2 points in dim 2 or 3; got n={n}, dim={dim}.")

    def p_of(args):
        return parameters(free_chain, args)

    def points(q):
        return q.reshape(n, dim)

    def links(q, args):
        x = points(q)
        return jnp.linalg.norm(x[1:] - x[:-1], axis=-1) - jnp.broadcast_to(p_of(args)["l"], (n - 1,))

    lagrangian = lagrangian_from_positions(
        points,
        lambda a: jnp.broadcast_to(jnp.asarray(p_of(a)["m"]), (n,)),
        gravity=lambda a: p_of(a)["g"],
    )
    return System(lagrangian, holonomic=links)


@model({"M": 1.0, "m": 0.1, "l": 1.0, "g": 9.81, "force": 0.0}, allow_extra=True)
def cart_pole(control: Callable | None = None) -> System:
    r"""A cart of mass ``M`` on a horizontal track carrying a uniform pole (rod) of mass ``m``, length ``l``.

    ``q = (x, θ)``: cart position and pole angle from the **upward** vertical (upright is 0,
    positive tilts towards +x). The pole is a [`RigidBody2D`][jaxlag.coordinates.RigidBody2D] with its
    centre at ``(x + ½ l sin θ, ½ l cos θ)`` and ``I = m l²/12``:

        L = ½ (M + m) ẋ² + ½ m l ẋ θ̇ cos θ + ⅙ m l² θ̇² − ½ m g l cos θ.

    The input is a horizontal force ``u`` (a scalar) on the cart, the system's ``actuation``
    ``Q_u = (u, 0)``. Its control law is ``control(q, qd, [t], [args])`` if given (a feedback
    law, a time table in ``args``, or both), else the parameter ``force`` (a constant);
    [`jaxlag.analysis.linearize`][jaxlag.analysis.linearize] gives ``B = ∂(q̇, q̈)/∂u`` and, with a law, the
    feedback
    ``∂u/∂(q, q̇)``. ``cart_pole().with_control(law)`` is the same model with another law.
    Extra keys in ``args`` are allowed for the keys that ``control`` reads (controller gains,
    tables); any other key is refused, with the closest parameter name (not after
    ``with_control``, whose law is not watched). Parameters: ``M``, ``m``, ``l``, ``g``,
    ``force``.
    """

    def p_of(args):
        return parameters(cart_pole, args)

    def cart(q):
        return jnp.stack([q[0], jnp.zeros((), q.dtype)])

    def pole_pose(q, args):
        x, th = q
        half = 0.5 * p_of(args)["l"]
        return jnp.stack([x + half * jnp.sin(th), half * jnp.cos(th), -th])

    pole = RigidBody2D(
        pole_pose, mass=lambda a: p_of(a)["m"], inertia=lambda a: p_of(a)["m"] * p_of(a)["l"] ** 2 / 12.0
    )
    lagrangian = lagrangian_from_positions(
        cart, lambda a: p_of(a)["M"], gravity=lambda a: p_of(a)["g"], bodies=[pole]
    )

    def actuation(q, qd, u):  # Q_u = (u, 0): a horizontal force on the cart
        return jnp.stack([jnp.reshape(u, ()), jnp.zeros((), q.dtype)])

    def constant_force(q, qd, args):  # the parameter `force`; every key of args is checked
        if isinstance(args, Mapping):
            check_keys(cart_pole, args)
        return jnp.asarray(p_of(args)["force"], q.dtype)

    if control is None:
        return System(lagrangian, actuation=actuation, control=constant_force)
    user = wrap_state_function(control, "cart-pole control")

    def law(q, qd, t, args):  # the user's control; keys it does not read are still checked
        u = jnp.asarray(_call_recording_reads(user, q, qd, t, args), q.dtype)
        if u.shape != ():
            raise ValueError(f"The cart-pole control must return a scalar force; got shape {u.shape}.")
        return u

    return System(lagrangian, actuation=actuation, control=law)


def _call_recording_reads(user, q, qd, t, args):
    """``user(q, qd, t=t, args=args)``; with a dict ``args``, also refuse the keys that neither
    the cart-pole nor the control reads (a misspelt parameter). Runs while tracing only."""
    if not isinstance(args, Mapping):
        return user(q, qd, t=t, args=args)
    reads = KeyReads(args)
    try:
        out = user(q, qd, t=t, args=reads)
    except Exception:  # noqa: BLE001 - a control that needs a real dict: call it with one, no check
        return user(q, qd, t=t, args=args)
    if not reads.everything:
        check_keys(cart_pole, args, reads.read, "the control")
    return out
