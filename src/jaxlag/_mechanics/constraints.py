r"""Constraints: Jacobians, acceleration-level right-hand sides and residuals.

Holonomic constraints ``f(q, t) = 0`` (m_h entries) contribute the rows ``J = ∂f/∂q`` and, at
acceleration level, ``J q̈ = −γ`` with

    γ = q̇ᵀ(∂²f/∂q²)q̇ + 2(∂²f/∂q∂t)q̇ + ∂²f/∂t²  =  d²/ds² f(q + s q̇, t + s) |_{s=0},

computed by one nested forward-mode ``jvp`` (never a dense Hessian). Their velocity-level form
is ``ḟ = J q̇ + ∂f/∂t = 0``.

Velocity (Pfaffian) constraints ``g(q, q̇, t) = A(q, t) q̇ + b(q, t) = 0`` (m_v entries) are
given as one function affine in ``q̇``; ``A = ∂g/∂q̇`` and, at acceleration level,
``A q̈ = −γ_v`` with ``γ_v = (∂g/∂q) q̇ + ∂g/∂t`` at fixed ``q̇``.

Stacked, the constraint rows are ``G = [J; A]`` and the right-hand side ``c = [−γ; −γ_v]``.
"""

import jax
import jax.numpy as jnp

from .lagrangian import as_time


def holonomic_residual(system, q, t, args):
    """``f(q, t)``, shape (m_h,)."""
    return jnp.asarray(system.holonomic(q, t=as_time(t, q), args=args), dtype=q.dtype)


def velocity_residual(system, q, qd, t, args):
    """``g(q, q̇, t) = A q̇ + b``, shape (m_v,)."""
    return jnp.asarray(system.velocity_constraints(q, qd, t=as_time(t, q), args=args), q.dtype)


def holonomic_terms(system, q, qd, t, args):
    """Return ``(f, ḟ, J, γ)`` for the holonomic constraints at a state."""
    t = as_time(t, q)

    def along_motion(s):
        return holonomic_residual(system, q + s * qd, t + s, args)

    def first_derivative(s):
        return jax.jvp(along_motion, (s,), (jnp.ones_like(s),))

    zero = jnp.zeros((), t.dtype)
    (f, f_dot), (_, gamma) = jax.jvp(first_derivative, (zero,), (jnp.ones_like(zero),))
    jac = holonomic_jacobian(system, q, t, args, f.shape[0])
    return f, f_dot, jac, gamma


def holonomic_jacobian(system, q, t, args, num_constraints):
    """``J = ∂f/∂q`` (m_h, n): reverse mode (m_h VJPs) when there are fewer constraints than
    coordinates, forward mode (n JVPs) otherwise. Measured on a 20-link Cartesian chain with
    20 constraints in 40 coordinates: 1.09× → 0.95× the hand-written KKT baseline."""
    residual = lambda x: holonomic_residual(system, x, t, args)  # noqa: E731
    return (jax.jacrev if num_constraints < q.shape[0] else jax.jacfwd)(residual)(q)


def velocity_terms(system, q, qd, t, args):
    """Return ``(g, A, γ_v)`` for the velocity constraints at a state."""
    t = as_time(t, q)

    def g_of(q_, t_):
        return velocity_residual(system, q_, qd, t_, args)

    g, gamma = jax.jvp(g_of, (q, t), (qd, jnp.ones_like(t)))
    a = jax.jacfwd(lambda v: velocity_residual(system, q, v, t, args))(qd)
    return g, a, gamma


def constraint_rows(system, q, qd, t, args, baumgarte=None):
    """Stacked constraint rows ``G`` (m, n) and acceleration right-hand side ``c`` (m,).

    ``G q̈ = c`` is the acceleration-level form of every constraint. With Baumgarte
    stabilization (``alpha``, ``beta``) the holonomic rows enforce
    ``f̈ + 2α ḟ + β² f = 0`` and the velocity rows ``ġ + 2α g = 0`` instead of ``f̈ = 0`` and ``ġ = 0``.
    """
    rows, rhs = [], []
    if system.holonomic is not None:
        f, f_dot, jac, gamma = holonomic_terms(system, q, qd, t, args)
        c = -gamma
        if baumgarte is not None:
            c = c - 2.0 * baumgarte.alpha * f_dot - baumgarte.beta**2 * f
        rows.append(jac)
        rhs.append(c)
    if system.velocity_constraints is not None:
        g, a, gamma_v = velocity_terms(system, q, qd, t, args)
        c = -gamma_v
        if baumgarte is not None:
            c = c - 2.0 * baumgarte.alpha * g
        rows.append(a)
        rhs.append(c)
    if not rows:
        return jnp.zeros((0, q.shape[0]), q.dtype), jnp.zeros((0,), q.dtype)
    return jnp.concatenate(rows, axis=0), jnp.concatenate(rhs)


def constraint_residuals(system, q, qd, t=0.0, args=None):
    """Residuals ``(f, ḟ, g)`` (holonomic position, holonomic velocity, velocity constraints).

    Empty arrays stand for constraints the system does not have.
    """
    empty = jnp.zeros((0,), q.dtype)
    f = f_dot = g = empty
    if system.holonomic is not None:
        t_ = as_time(t, q)
        f, f_dot = jax.jvp(
            lambda x, s: holonomic_residual(system, x, s, args), (q, t_), (qd, jnp.ones_like(t_))
        )
    if system.velocity_constraints is not None:
        g = velocity_residual(system, q, qd, t, args)
    return f, f_dot, g
