r"""Mechanics of a Lagrangian by automatic differentiation.

For ``L(q, q̇, t)`` the Euler–Lagrange equations with generalized forces ``Q``,

    d/dt ∂L/∂q̇ − ∂L/∂q = Q,

expand, with ``p = ∂L/∂q̇``, to ``M q̈ = F`` where

    M = ∂²L/∂q̇²                                     (mass matrix)
    F = ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t + Qⁿᶜ         (generalized forces)
    Qⁿᶜ = −∂R/∂q̇ + Q_ext + Q_u(q, q̇, u, t)          (Rayleigh dissipation, external forces,
                                                      actuation of the input u = control(q, q̇, t)).

``M`` and the velocity terms come from forward-over-reverse products: the gradient
``(∂L/∂q, ∂L/∂q̇)`` is pushed forward along ``(q̇, 0, 1)`` in ``(q, q̇, t)`` (giving
``(∂p/∂q) q̇ + ∂p/∂t``) and ``p`` along the n unit directions in ``q̇`` (the columns of ``M``).
No dense Hessian in ``q`` is ever formed.
"""

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike


def time_dtype(dtype) -> jnp.dtype:
    """The dtype of times for coordinates of ``dtype``: the same floating type, or JAX's default
    float for integer coordinates (no implicit promotion: valid under strict dtype promotion)."""
    return jnp.dtype(dtype) if jnp.issubdtype(dtype, jnp.floating) else jnp.dtype(jnp.result_type(float))


def as_time(t, q):
    return jnp.asarray(t, dtype=time_dtype(q.dtype))


def _unit_basis(x):
    """Rows of the identity, built from the state so XLA cannot hoist them out of the solver loop.

    A loop-invariant identity becomes a loop-carried boolean mask (while-loop-invariant code
    motion) and the tangent kernels ``select(mask, broadcast(cos q), 0)`` then evaluate their
    transcendentals n² times: measured 26.5 → 9.7 µs per mass matrix for a 20-link chain. The
    offset is 0 for every finite state.
    """
    n = x.shape[0]
    offset = jnp.isnan(x[0]).astype(jnp.int32)
    i = jnp.arange(n, dtype=jnp.int32)
    return (i[:, None] == i[None, :] + offset).astype(x.dtype)


def _velocity_terms(system, q, qd, t, args):
    """``(∂L/∂q, p, (∂p/∂q) q̇ + ∂p/∂t)`` by one ``jvp`` of the gradient along ``(q̇, 0, 1)``."""
    L = system.lagrangian

    def gradient(q_, qd_, t_):
        return jax.grad(lambda a, b, c: L(a, b, t=c, args=args), argnums=(0, 1))(q_, qd_, t_)

    (dL_dq, p), (_, dp_motion) = jax.jvp(gradient, (q, qd, t), (qd, jnp.zeros_like(qd), jnp.ones_like(t)))
    return dL_dq, p, dp_motion


def _mass_and_lagrangian_forces(system, q, qd, t, args):
    """``(M, F_L)`` from the system's dynamics (``t`` already an array)."""
    if system.constant_mass is not None:
        return system.constant_mass.matrix, system.dynamics.forces(system, q, qd, t, args)
    return system.dynamics.mass_and_forces(system, q, qd, t, args)


def mass_along(system, q, qd, t, args, basis):
    """Rows ``(∂p/∂q̇) e`` for each row ``e`` of ``basis`` (``M`` itself for the identity, as
    ``M`` is symmetric): ``jvp``s of ``p`` in ``q̇`` alone, with ``t`` already an array."""

    def momentum(v):
        return jax.grad(lambda b: system.lagrangian(q, b, t=t, args=args))(v)

    return jax.vmap(lambda e: jax.jvp(momentum, (qd,), (e,))[1])(basis)


def nonconservative_forces(system, q, qd, t, args):
    """``Qⁿᶜ = −∂R/∂q̇ + Q_ext(q, q̇, t) + Q_u(q, q̇, u, t)``; zero when none is given."""
    total = jnp.zeros_like(q)
    if system.dissipation is not None:
        total = total - jax.grad(lambda v: system.dissipation(q, v, t=t, args=args))(qd)
    if system.forces is not None:
        total = total + jnp.asarray(system.forces(q, qd, t=t, args=args), dtype=q.dtype)
    if system.actuation is not None:
        total = total + actuation_forces(system, q, qd, t, args)
    return total


def control_input(system, q, qd, t: ArrayLike = 0.0, args=None):
    """The input ``u = control(q, q̇, t)`` of the system's control law (a scalar or (k,))."""
    if system.actuation is None:
        raise ValueError(
            "This system has no control input: give jl.System(..., actuation=Q_u, control=law), "
            "with Q_u(q, qd, u, [t], [args]) the generalized forces of the input u."
        )
    if system.control is None:
        raise ValueError(
            "This system has an actuation Q_u(q, qd, u) but no control law giving its input u. "
            "Give one: jl.System(..., control=law) or system.with_control(law), with "
            "u = law(q, qd, [t], [args]), e.g. a time table lambda q, qd, t, args: args['u'](t) "
            "for an open loop (jaxlag.inputs). jaxlag.analysis.linearize takes u= instead."
        )
    u = system.control(q, qd, t=as_time(t, q), args=args)
    return jnp.asarray(u, dtype=q.dtype)


def actuation_forces(system, q, qd, t, args, u=None):
    """``Q_u(q, q̇, u, t)``, shape (n,), with ``u`` from the control law unless given."""
    t = as_time(t, q)
    if u is None:
        u = control_input(system, q, qd, t, args)
    return jnp.asarray(system.actuation(q, qd, u, t=t, args=args), dtype=q.dtype)


def mass_matrix(system, q, qd, t: ArrayLike = 0.0, args=None):
    """``M = ∂²L/∂q̇²``, shape (n, n), from the system's ``dynamics``."""
    if system.constant_mass is not None:
        return jnp.asarray(system.constant_mass.matrix, dtype=q.dtype)
    return system.dynamics.mass_matrix(system, q, qd, as_time(t, q), args)


def mass_and_forces(system, q, qd, t, args):
    """``(M, F)`` of ``M q̈ = F`` with every generalized force included: ``M`` and ``F_L`` from
    the system's ``dynamics``, ``Qⁿᶜ`` from its dissipation, forces and actuation."""
    t = as_time(t, q)
    mass, force = _mass_and_lagrangian_forces(system, q, qd, t, args)
    return mass, force + nonconservative_forces(system, q, qd, t, args)


def mass_solver(system, q, qd, t, args):
    """``b ↦ M⁻¹ b`` at a state: ``M`` factored once (or the precomputed constant inverse)."""
    if system.constant_mass is not None:
        return system.constant_mass.solve
    # By default the system's mass_solve (jaxlag._mechanics.mass_solve) factors M: checked
    # Cholesky, or NaN on failure; a dynamics object may apply M⁻¹ without forming M.
    return system.dynamics.mass_solver(system, q, qd, as_time(t, q), args)


def mass_solver_and_forces(system, q, qd, t, args):
    """``(b ↦ M⁻¹ b, F)``: the right-hand side of ``M q̈ = F`` with ``M`` ready to solve with."""
    if system.constant_mass is not None:
        return system.constant_mass.solve, mass_and_forces(system, q, qd, t, args)[1]
    t = as_time(t, q)
    solve, force = system.dynamics.solver_and_forces(system, q, qd, t, args)
    return solve, force + nonconservative_forces(system, q, qd, t, args)


def generalized_forces(system, q, qd, t=0.0, args=None):
    """``F = ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t − ∂R/∂q̇ + Q_ext``, shape (n,)."""
    return mass_and_forces(system, q, qd, t, args)[1]


def momenta(system, q, qd, t=0.0, args=None):
    """Generalized momenta ``p = ∂L/∂q̇``, shape (n,)."""
    t = as_time(t, q)
    return jax.grad(lambda v: system.lagrangian(q, v, t=t, args=args))(qd)


def energy(system, q, qd, t=0.0, args=None):
    """Energy function (Jacobi integral) ``h = q̇·∂L/∂q̇ − L``; conserved when ``∂L/∂t = 0``
    and there is no dissipation, no external force and no rheonomic constraint."""
    t = as_time(t, q)
    value, p = jax.value_and_grad(lambda v: system.lagrangian(q, v, t=t, args=args))(qd)
    return jnp.dot(qd, p) - value


def lagrangian_value(system, q, qd, t=0.0, args=None):
    """``L(q, q̇, t)`` through the calling convention."""
    return system.lagrangian(q, qd, t=as_time(t, q), args=args)


def unconstrained_accelerations(system, q, qd, t, args):
    """``q̈ = M⁻¹ F`` for a system without constraints."""
    solve, force = mass_solver_and_forces(system, q, qd, t, args)
    return solve(force)


def dissipated_power(system, q, qd, t=0.0, args=None):
    """Power removed by Rayleigh dissipation, ``q̇·∂R/∂q̇`` (``= 2R`` for ``R`` quadratic in q̇)."""
    if system.dissipation is None:
        return jnp.zeros((), q.dtype)
    t = as_time(t, q)
    return jnp.dot(qd, jax.grad(lambda v: system.dissipation(q, v, t=t, args=args))(qd))


def input_power(system, q, qd, t=0.0, args=None):
    """Power delivered by the external generalized forces and the actuation, ``q̇·(Q_ext + Q_u)``."""
    t = as_time(t, q)
    power = jnp.zeros((), q.dtype)
    if system.forces is not None:
        power = power + jnp.dot(qd, jnp.asarray(system.forces(q, qd, t=t, args=args), dtype=q.dtype))
    if system.actuation is not None:
        power = power + jnp.dot(qd, actuation_forces(system, q, qd, t, args))
    return power
