r"""Structure-preserving constrained integration: RATTLE and variational integrators.

`simulate_variational` integrates a [`System`][jaxlag.System] with holonomic constraints
``f(q, t) = 0`` by a *constrained variational integrator*: instead of discretizing the
equations of motion it discretizes the action. A discrete Lagrangian
``L_d(q_k, q_{k+1}) ≈ ∫ L dt`` over one step of size ``h`` gives, in position–momentum form
(Marsden & West 2001, §3.5; Hairer, Lubich & Wanner, *Geometric Numerical Integration* VII.1),

    p_k + D₁L_d(q_k, q_{k+1}) + f⁻_k + (h/2) J(q_k)ᵀ λ_k = 0,        f(q_{k+1}, t_{k+1}) = 0,
    p_{k+1} = D₂L_d(q_k, q_{k+1}) + f⁺_k + (h/2) J(q_{k+1})ᵀ μ_k,
    J(q_{k+1}) q̇_{k+1} + ∂f/∂t = 0   with   p_{k+1} = ∂L/∂q̇(q_{k+1}, q̇_{k+1}, t_{k+1}).

The first line is the implicit *position stage* (unknowns ``q_{k+1}``, ``λ_k``), the last two the
*velocity stage* (unknowns ``q̇_{k+1}``, ``μ_k``; linear when ``L`` is quadratic in ``q̇``), which
puts ``(q_{k+1}, p_{k+1})`` back on the cotangent bundle of the constraint manifold — RATTLE's
second stage. Eliminating the momenta gives the discrete Euler–Lagrange equations

    D₂L_d(q_{k−1}, q_k) + D₁L_d(q_k, q_{k+1}) + f⁺_{k−1} + f⁻_k + h J(q_k)ᵀ (μ_{k−1} + λ_k)/2 = 0,

the discrete counterpart of ``d/dt ∂L/∂q̇ − ∂L/∂q = Jᵀλ + Qⁿᶜ`` with jaxlag's sign convention
(``M q̈ = F + Jᵀλ``), so the multipliers have the sign of `Trajectory.multipliers`.

Discrete Lagrangians (both second order, symmetric):

* ``method=jl.Rattle()``: trapezoidal ``L_d = (h/2)[L(q_k, v, t_k) + L(q_{k+1}, v, t_{k+1})]``,
  ``v = (q_{k+1} − q_k)/h``. For ``L = ½ q̇ᵀMq̇ − V(q)`` with constant ``M`` this is exactly
  RATTLE (Störmer–Verlet with constraints): the positions are explicit given ``λ_k``, so each
  step solves only the ``m`` constraint equations for ``λ_k`` by Newton (SHAKE) and the velocity
  stage is one linear solve. For ``M(q)`` the position stage is a Newton solve in
  ``(q_{k+1}, λ_k)``.
  Needs ``L`` quadratic in ``q̇``.
* ``method=jl.VariationalMidpoint()``: midpoint ``L_d = h L((q_k + q_{k+1})/2, v, t_k + h/2)``, for any
  regular ``L(q, q̇, t)``; position stage by Newton in ``(q_{k+1}, λ_k)``, velocity stage by Newton
  in ``(q̇_{k+1}, μ_k)`` unless ``L`` is quadratic in ``q̇`` (then linear).
* ``method=None`` (default): `Rattle` when ``L`` is recognisably quadratic in ``q̇``,
  else `VariationalMidpoint`.

Higher order: ``order=4`` or ``6`` composes the symmetric step with Yoshida's coefficients (3 or
7 substeps per step, some of negative size); the composition is still symplectic, symmetric and
constraint-preserving, with energy error ``O(h⁴)`` or ``O(h⁶)``.

Non-conservative forces enter through the discrete Lagrange–d'Alembert principle,
``f^± = (h/2) Qⁿᶜ`` at the quadrature node(s) of the rule, ``Qⁿᶜ = −∂R/∂q̇ + Q_ext``.

Properties (float64): ``f = 0`` and ``J q̇ + ∂f/∂t = 0`` hold to the Newton tolerance at every
step; the map ``(q_k, p_k) ↦ (q_{k+1}, p_{k+1})`` is symplectic on the constrained phase space, so
the energy error of an autonomous conservative system stays bounded (``O(h²)``, no drift) over
exponentially long times; momenta of symmetries of ``L_d`` and ``f`` are conserved to round-off
(discrete Noether). Implicit steps use `optimistix.root_find` with
`optimistix.Newton`; gradients go through them by the implicit function theorem
(`optimistix.ImplicitAdjoint`), not by unrolling Newton.

Which structure ``L`` has is read off its jaxpr (a static, conservative dependence analysis): a
``q̇``-independent ``∂²L/∂q̇²`` means quadratic, a ``(q, t)``-independent ``∂L/∂q̇`` means constant
``M`` (explicit positions). A Lagrangian written so that the analysis cannot see this (e.g.
``jnp.linalg.norm(qd)**2``) only takes a slower path; with ``method=jl.Rattle()`` it is then checked
numerically at the initial state instead.
"""

import dataclasses
from typing import ClassVar, NamedTuple, cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.typing import ArrayLike
from jaxtyping import Array, Float, Int

from . import _compile as compilation
from ._checks import Checks, validate_initial_state
from ._conventions import as_array_leaves
from ._custom_types import Args, Coordinates, RealScalarLike, Validated, Velocities
from ._errors import SimulationError, compiled_check, on_failure
from ._mechanics import constraints as _constraints
from ._mechanics.dependence import may_depend
from ._mechanics.kkt import accelerations_and_multipliers, solve_kkt
from ._mechanics.lagrangian import as_time, mass_matrix, nonconservative_forces
from ._mechanics.linalg import solve_spd
from ._misc import is_concrete
from ._system import System
from ._trajectory import Trajectory


class AbstractVariationalMethod(eqx.Module):
    """The discrete Lagrangian of [`simulate_variational`][jaxlag.simulate_variational]:
    [`Rattle`][jaxlag.Rattle]
    or [`VariationalMidpoint`][jaxlag.VariationalMidpoint] (``method=None`` picks one from the structure of
    ``L``)."""

    rule: ClassVar[str]


class Rattle(AbstractVariationalMethod):
    r"""Trapezoidal discrete Lagrangian
    ``L_d = (h/2)[L(q_k, v, t_k) + L(q_{k+1}, v, t_{k+1})]``, ``v = (q_{k+1} − q_k)/h``: RATTLE
    (Störmer–Verlet with constraints) for ``L = ½ q̇ᵀM(q)q̇ + b(q)·q̇ − V(q)``. Needs ``L``
    quadratic in ``q̇`` (checked: statically from its jaxpr, else numerically at the initial
    state). With constant ``M`` the positions are explicit and each step solves only the ``m``
    constraint equations for ``λ_k``."""

    rule: ClassVar[str] = "trapezoid"


class VariationalMidpoint(AbstractVariationalMethod):
    r"""Midpoint discrete Lagrangian ``L_d = h L((q_k + q_{k+1})/2, v, t_k + h/2)`` for any
    regular ``L(q, q̇, t)``: the position stage is a Newton solve in ``(q_{k+1}, λ_k)``, the
    velocity stage a Newton solve in ``(q̇_{k+1}, μ_k)`` (linear when ``L`` is quadratic in
    ``q̇``)."""

    rule: ClassVar[str] = "midpoint"


# --------------------------------------------------------------------------- structure of L
class LagrangianStructure(NamedTuple):
    """What the integrator may exploit, established statically (conservatively) from the jaxpr.

    ``quadratic``: ``∂²L/∂q̇²`` does not depend on ``q̇`` (``L`` is at most quadratic in ``q̇``:
    ``p = M(q, t) q̇ + b(q, t)``, so the velocity stage is a linear solve).
    ``constant_mass``: additionally ``p = ∂L/∂q̇`` depends on neither ``q`` nor ``t`` (``M``, ``b``
    constant), so RATTLE's positions are explicit given the multipliers.
    """

    quadratic: bool
    constant_mass: bool


def lagrangian_structure(system: System, q, qd, t: ArrayLike = 0.0, args=None) -> LagrangianStructure:
    """Analyse ``L`` statically (shapes only); see `LagrangianStructure`."""
    q = jnp.asarray(q)
    qd = jnp.asarray(qd, q.dtype)
    t = as_time(t, q)

    def momentum(q_, qd_, t_, args_, system_):
        return jax.grad(lambda v: system_.lagrangian(q_, v, t=t_, args=args_))(qd_)

    def hessian_product(q_, qd_, t_, args_, system_, direction):
        # M u by forward-over-reverse along an input direction (jacfwd's basis would depend on
        # q̇ through an internal trick and hide the structure).
        return jax.jvp(lambda v: momentum(q_, v, t_, args_, system_), (qd_,), (direction,))[1]

    try:
        on_qd = may_depend(hessian_product, (q, qd, t, args, system, qd))[0][1]
        if on_qd:
            return LagrangianStructure(False, False)
        dep, _ = may_depend(momentum, (q, qd, t, args, system))
        return LagrangianStructure(True, not (dep[0] or dep[2]))
    except Exception:  # noqa: BLE001 - the analysis is an optimisation; never fail because of it
        return LagrangianStructure(False, False)


def _check_quadratic(system, q, qd, t, args):
    """Numerical check at one state that ``L`` is quadratic in ``q̇``.

    Returns the third finite difference of ``s ↦ L(q, s u)`` along a generic direction ``u``
    (zero for a quadratic), relative to the size of ``L``.
    """
    scale = 1.0 + jnp.max(jnp.abs(qd))
    direction = qd + scale * jnp.cos(jnp.arange(qd.shape[0], dtype=q.dtype) + 0.5)
    values = jnp.stack([system.lagrangian(q, s * direction, t=t, args=args) for s in (0.0, 1.0, 2.0, 3.0)])
    third = values[3] - 3 * values[2] + 3 * values[1] - values[0]
    return jnp.abs(third) / (1.0 + jnp.max(jnp.abs(values)))


# --------------------------------------------------------------------------- the discrete pieces
def _lagrangian_gradient(system, q, v, t, args):
    """``(∂L/∂q, ∂L/∂q̇)`` at ``(q, v, t)``."""
    return jax.grad(lambda a, b: system.lagrangian(a, b, t=t, args=args), argnums=(0, 1))(q, v)


def _has_forces(system):
    return system.dissipation is not None or system.forces is not None or system.actuation is not None


def _discrete_derivatives(system, rule, q0, dq, t0, h, args):
    """``(D₁L_d + f⁻, D₂L_d + f⁺)`` at ``(q_k, q_k + Δq)`` for the midpoint or trapezoidal rule.

    The increment ``Δq`` is the unknown rather than ``q_{k+1}``: ``v = Δq/h`` then carries no
    cancellation error (``(q_{k+1} − q_k)/h`` would lose ``eps·|q|/h`` at every step).
    """
    v = dq / h
    q1 = q0 + dq
    if rule == "midpoint":
        qm, tm = q0 + 0.5 * dq, t0 + 0.5 * h
        lq, lv = _lagrangian_gradient(system, qm, v, tm, args)
        d1, d2 = 0.5 * h * lq - lv, 0.5 * h * lq + lv
        if _has_forces(system):
            force = 0.5 * h * nonconservative_forces(system, qm, v, tm, args)
            d1, d2 = d1 + force, d2 + force
        return d1, d2
    t1 = t0 + h
    lq0, lv0 = _lagrangian_gradient(system, q0, v, t0, args)
    lq1, lv1 = _lagrangian_gradient(system, q1, v, t1, args)
    lv = 0.5 * (lv0 + lv1)
    d1, d2 = 0.5 * h * lq0 - lv, 0.5 * h * lq1 + lv
    if _has_forces(system):
        d1 = d1 + 0.5 * h * nonconservative_forces(system, q0, v, t0, args)
        d2 = d2 + 0.5 * h * nonconservative_forces(system, q1, v, t1, args)
    return d1, d2


def _constraint_jacobians(system, q, t, args):
    """``(f, J, ∂f/∂t)`` at ``(q, t)``."""

    def f_of(x, s):
        return _constraints.holonomic_residual(system, x, s, args)

    f = f_of(q, t)
    jac, f_t = jax.jacfwd(f_of, argnums=(0, 1))(q, t)
    return f, jac, f_t


def _project_with_inverse(minv, rhs, jac, c):
    """Solve ``M x = rhs + Jᵀν``, ``J x = c`` given ``M⁻¹``; return ``(x, ν)``."""
    free = minv @ rhs
    minv_jt = minv @ jac.T
    nu = solve_spd(jac @ minv_jt, c - jac @ free)
    return free + minv_jt @ nu, nu


# --------------------------------------------------------------------------- configuration
#: Symmetric compositions of the second-order step (Yoshida 1990): substep sizes γᵢ h.
_CBRT2 = 2.0 ** (1.0 / 3.0)
_TRIPLE_JUMP = (1.0 / (2.0 - _CBRT2), -_CBRT2 / (2.0 - _CBRT2))
_YOSHIDA6 = (0.784513610477560, 0.235573213359357, -1.17767998417887)
COMPOSITIONS = {
    2: (1.0,),
    4: (_TRIPLE_JUMP[0], _TRIPLE_JUMP[1], _TRIPLE_JUMP[0]),
    6: _YOSHIDA6 + (1.0 - 2.0 * sum(_YOSHIDA6),) + _YOSHIDA6[::-1],
}


class _Scheme(eqx.Module):
    """Static choices of one integration (hashable, part of the compilation key)."""

    rule: str  # "trapezoid" (RATTLE) or "midpoint" (variational)
    quadratic: bool
    constant_mass: bool
    constrained: bool
    order: int
    rtol: float
    atol: float
    max_newton_steps: int

    @property
    def explicit_positions(self):
        # Trapezoid + constant p(q̇) (no velocity-dependent forces): q_{k+1} is affine in λ_k.
        return self.rule == "trapezoid" and self.constant_mass

    @property
    def gammas(self):
        return COMPOSITIONS[self.order]

    def solver(self):
        return optx.Newton(rtol=self.rtol, atol=self.atol)


# (J, ∂L/∂q) at a state, reused by the next step; None where the scheme does not use them.
_Local = tuple[Float[Array, "m n"] | None, Float[Array, " n"] | None]


class _Step(eqx.Module):
    """What one step returns: the new state and its multipliers (``m`` holonomic rows)."""

    q: Float[Array, " n"]
    p: Float[Array, " n"]
    qd: Float[Array, " n"]
    lam: Float[Array, " m"]  # position-stage multiplier λ_k
    mu: Float[Array, " m"]  # velocity-stage multiplier μ_k
    local: _Local
    secant: Float[Array, " n"]  # Δq/h
    iterations: Int[Array, ""]
    result: optx.RESULTS


def _root(fn, y0, ctx, scheme):
    sol = optx.root_find(fn, scheme.solver(), y0, ctx, max_steps=scheme.max_newton_steps, throw=False)
    return sol.value, jnp.asarray(sol.stats["num_steps"], jnp.int32), sol.result


# The multipliers are solved for as impulses Λ = (h²/2) λ: λ itself is determined by a step only
# to ~ eps·|q|/h² (the constraint rows see it through h²), so tolerances on Λ are in units of
# M·q, like the position residual, and meaningful at every step size.


def _position_residual_full(y, ctx):
    system, rule, q0, p0, t0, h, jac0, args = ctx
    dq, impulse = y if jac0 is not None else (y, None)
    d1, _ = _discrete_derivatives(system, rule, q0, dq, t0, h, args)
    # h · (p_k + D₁L_d + f⁻ + (h/2)Jᵀλ): in units of M·q, balanced against f's rows.
    r1 = h * (p0 + d1)
    if jac0 is None:
        return r1
    return r1 + jac0.T @ impulse, _constraints.holonomic_residual(system, q0 + dq, t0 + h, args)


def _position_residual_explicit(impulse, ctx):
    system, q0, dq_free, gain, t1, args = ctx
    return _constraints.holonomic_residual(system, q0 + (dq_free + gain @ impulse), t1, args)


def _velocity_residual(y, ctx):
    system, q1, p_tilde, t1, jac1, f_t1, args = ctx
    qd1, nu = y if jac1 is not None else (y, None)
    _, lv = _lagrangian_gradient(system, q1, qd1, t1, args)
    r1 = lv - p_tilde
    if jac1 is None:
        return r1
    return r1 - jac1.T @ nu, jac1 @ qd1 + f_t1


def _velocity_stage(scheme, system, q1, p_tilde, t1, args, qd_guess, constants):
    """``(q̇_{k+1}, p_{k+1}, ν, J_{k+1})`` with ``ν = (h/2) μ_k``; plus Newton statistics.

    Solves ``∂L/∂q̇(q_{k+1}, q̇) = p̃ + J_{k+1}ᵀν``, ``J_{k+1} q̇ + ∂f/∂t = 0``: the discrete
    Legendre transform with the momentum projected onto the constraint's cotangent space.
    """
    if scheme.constrained:
        _, jac1, f_t1 = _constraint_jacobians(system, q1, t1, args)
    else:
        jac1 = f_t1 = None
    no_iterations = jnp.zeros((), jnp.int32)
    success = optx.RESULTS.successful
    empty = jnp.zeros((0,), q1.dtype)
    if scheme.quadratic:
        minv = mass = None
        if scheme.constant_mass:
            minv, b = constants
        else:
            # p = M q̇ + b for every q̇; evaluated at the guess, not at q̇ = 0, where a Lagrangian
            # such as ½|q̇|² written with a norm has no derivative.
            mass = mass_matrix(system, q1, qd_guess, t1, args)
            b = _lagrangian_gradient(system, q1, qd_guess, t1, args)[1] - mass @ qd_guess
        diagonal = bool(getattr(system, "diagonal_mass", False))
        if jac1 is None or f_t1 is None:  # both or neither (scheme.constrained)
            qd1 = minv @ (p_tilde - b) if minv is not None else solve_spd(mass, p_tilde - b, diagonal)
            return qd1, p_tilde, empty, jac1, no_iterations, success
        if minv is not None:
            qd1, nu = _project_with_inverse(minv, p_tilde - b, jac1, -f_t1)
        else:
            qd1, nu = solve_kkt(mass, p_tilde - b, jac1, -f_t1, diagonal_mass=diagonal)
        return qd1, p_tilde + jac1.T @ nu, nu, jac1, no_iterations, success
    ctx = (system, q1, p_tilde, t1, jac1, f_t1, args)
    if jac1 is None:
        qd1, iterations, result = _root(_velocity_residual, qd_guess, ctx, scheme)
        return qd1, p_tilde, empty, jac1, iterations, result
    y0 = (qd_guess, jnp.zeros((jac1.shape[0],), q1.dtype))
    (qd1, nu), iterations, result = _root(_velocity_residual, y0, ctx, scheme)
    return qd1, p_tilde + jac1.T @ nu, nu, jac1, iterations, result


def _local_terms(scheme, system, q, qd, t, args):
    """``(J, ∂L/∂q)`` at a state, as `_step` hands them on (``None`` where unused)."""
    jac = _constraint_jacobians(system, q, t, args)[1] if scheme.constrained else None
    force = _lagrangian_gradient(system, q, qd, t, args)[0] if scheme.explicit_positions else None
    return jac, force


def _step(scheme, system, args, constants, h, t0, q0, p0, local0, guess, qd_guess):
    """One step ``(q_k, p_k) ↦ (q_{k+1}, p_{k+1})`` of size ``h`` (may be negative).

    ``guess = (Δq, Λ_k)`` is the Newton starting point, ``local0 = (J_k, ∂L/∂q|_k)``.
    """
    t1 = t0 + h
    jac0, lq0 = local0
    lq1 = None
    if scheme.explicit_positions:
        # RATTLE/SHAKE: p_{k+½} = p_k + (h/2)(∂L/∂q|_k + J_kᵀλ_k),
        # q_{k+1} = q_k + h M⁻¹(p_{k+½} − b).
        minv, b = constants
        p_half = p0 + 0.5 * h * lq0
        dq = h * (minv @ (p_half - b))
        if jac0 is not None:
            gain = minv @ jac0.T
            impulse, iterations, result = _root(
                _position_residual_explicit, guess[1], (system, q0, dq, gain, t1, args), scheme
            )
            dq = dq + gain @ impulse
            p_half = p_half + jac0.T @ impulse / h
        else:
            impulse, result = guess[1], optx.RESULTS.successful
            iterations = jnp.zeros((), jnp.int32)
        q1 = q0 + dq
        lq1 = _lagrangian_gradient(system, q1, qd_guess, t1, args)[0]  # independent of q̇ here
        p_tilde = p_half + 0.5 * h * lq1
    else:
        ctx = (system, scheme.rule, q0, p0, t0, h, jac0, args)
        if jac0 is None:
            dq, iterations, result = _root(_position_residual_full, guess[0], ctx, scheme)
            impulse = guess[1]
        else:
            (dq, impulse), iterations, result = _root(_position_residual_full, guess, ctx, scheme)
        q1 = q0 + dq
        _, p_tilde = _discrete_derivatives(system, scheme.rule, q0, dq, t0, h, args)
    qd1, p1, nu, jac1, v_iterations, v_result = _velocity_stage(
        scheme, system, q1, p_tilde, t1, args, qd_guess, constants
    )
    result = optx.RESULTS.where(result == optx.RESULTS.successful, v_result, result)
    lam = 2.0 * impulse / (h * h)
    return _Step(q1, p1, qd1, lam, 2.0 * nu / h, (jac1, lq1), dq / h, iterations + v_iterations, result)


# --------------------------------------------------------------------------- the integration
class _Carry(eqx.Module):
    """The state of the integration loop after step k (``m`` holonomic rows)."""

    q: Float[Array, " n"]
    p: Float[Array, " n"]
    qd: Float[Array, " n"]
    local: _Local  # (J, ∂L/∂q) at q_k
    # (q_k − q_{k−1})/h_{k−1} and h_{k−1}: for the Newton starting point
    secant: tuple[Float[Array, " n"], Float[Array, ""]]
    lams: tuple[Float[Array, " m"], Float[Array, " m"]]  # the last two λ, for extrapolation
    mu: Float[Array, " m"]  # μ_{k−1}: velocity-stage multiplier that brought the state to q_k
    step: Int[Array, ""]  # macro-step index k
    iterations: Int[Array, ""]  # total Newton iterations
    max_iterations: Int[Array, ""]
    failed_step: Int[Array, ""]  # first macro step whose Newton solve failed, −1 if none
    result: optx.RESULTS


def _substep(scheme, system, args, constants, h, t, carry: _Carry):
    """One step of size ``h`` from time ``t``; returns the new carry and λ of this step."""
    v_prev, h_prev = carry.secant
    lam1, lam2 = carry.lams
    # Starting point accurate to O(h³): the last secant velocity sits at t − h_prev/2, the current
    # velocity at t, so their difference gives the acceleration. λ by linear extrapolation
    # (uniform steps) or held (compositions, where the substep sizes jump).
    accel = (carry.qd - v_prev) / (0.5 * h_prev)
    guess_dq = h * (carry.qd + 0.5 * h * accel)
    lam_guess = 2.0 * lam1 - lam2 if scheme.order == 2 else lam1
    guess = (guess_dq, 0.5 * h * h * lam_guess)
    out = _step(scheme, system, args, constants, h, t, carry.q, carry.p, carry.local, guess, carry.qd)
    ok = out.result == optx.RESULTS.successful
    first_failure = (carry.failed_step < 0) & ~ok
    new = dataclasses.replace(
        carry,
        q=out.q,
        p=out.p,
        qd=out.qd,
        local=out.local,
        secant=(out.secant, h),
        lams=(out.lam, lam1),
        mu=out.mu,
        iterations=carry.iterations + out.iterations,
        failed_step=jnp.where(first_failure, carry.step, carry.failed_step),
        result=optx.RESULTS.where(first_failure, out.result, carry.result),
    )
    return new, out.lam, out.iterations


def _advance(scheme, system, args, constants, h, t0, carry: _Carry):
    """One (possibly composed) step of size ``h``; returns the new carry and its first λ."""
    t = t0 + h * carry.step.astype(carry.q.dtype)
    gammas = scheme.gammas
    if len(gammas) == 1:
        carry, lam, iterations = _substep(scheme, system, args, constants, h, t, carry)
        first_lam = lam
    else:
        offsets = np.concatenate([[0.0], np.cumsum(gammas)[:-1]])

        def sub(c, gamma_offset):
            gamma, offset = gamma_offset
            c, lam, iterations = _substep(scheme, system, args, constants, gamma * h, t + offset * h, c)
            return c, (lam, iterations)

        schedule = (jnp.asarray(gammas, carry.q.dtype), jnp.asarray(offsets, carry.q.dtype))
        carry, (lams, iterations) = jax.lax.scan(sub, carry, schedule)
        first_lam, iterations = lams[0], jnp.sum(iterations, dtype=jnp.int32)
    carry = dataclasses.replace(
        carry, step=carry.step + 1, max_iterations=jnp.maximum(carry.max_iterations, iterations)
    )
    return carry, first_lam


_FAILURE = (
    "jaxlag.simulate_variational: an implicit step did not converge (Newton iteration of the "
    "position or velocity stage hit max_newton_steps or produced non-finite values). "
    "The step size dt is most likely too large for this motion: reduce dt (Newton starts from an "
    "extrapolation of the previous steps, accurate to O(dt³)). Also check that the constraints "
    "can be satisfied near the motion, that the mass matrix stays positive definite, and that "
    "newton_atol is above the round-off of your residuals (they are in the units of f and of "
    "M·q). Call with throw=False to get the trajectory anyway: traj.stats['failed_step'] is the "
    "first failing step and traj.result says why."
)


@compilation.filter_jit
def _integrate(scheme, system, q0, qd0, t0, dt, args, num_steps, save_every, throw, check, tolerance):
    system.check(q0, qd0, t0, args)
    if check:
        q0, qd0 = validate_initial_state(system, q0, qd0, t0, args, tolerance)
    h = jnp.asarray(dt, q0.dtype)
    t0 = jnp.asarray(t0, q0.dtype)
    p0 = jax.grad(lambda v: system.lagrangian(q0, v, t=t0, args=args))(qd0)
    if scheme.constant_mass:
        mass = mass_matrix(system, q0, qd0, t0, args)
        constants = (solve_spd(mass, jnp.eye(q0.shape[0], dtype=q0.dtype)), p0 - mass @ qd0)
    else:
        constants = None
    # Start-up values from the continuous motion: q̈₀ and λ(t₀) of the KKT system.
    qdd0, lam0, _ = accelerations_and_multipliers(system, q0, qd0, t0, args)
    zero = jnp.zeros((), jnp.int32)
    carry = _Carry(
        q=q0,
        p=p0,
        qd=qd0,
        local=_local_terms(scheme, system, q0, qd0, t0, args),
        secant=(qd0 - 0.5 * h * qdd0, h),
        lams=(lam0, lam0),
        mu=lam0,
        step=zero,
        iterations=zero,
        max_iterations=zero,
        failed_step=jnp.asarray(-1, jnp.int32),
        result=optx.RESULTS.successful,
    )

    def block(carry, _):
        def inner(c, _):
            return _advance(scheme, system, args, constants, h, t0, c)

        carry, lams = jax.lax.scan(inner, carry, None, length=save_every)
        # λ_k of the block's first step belongs to the state the block started from.
        return carry, (carry.q, carry.qd, carry.mu, lams[0])

    num_saves = num_steps // save_every
    last, (qs, qds, mus, lams_first) = jax.lax.scan(jax.checkpoint(block), carry, None, length=num_saves)
    # The discrete multiplier at a saved state q_k is the DEL one, (μ_{k−1} + λ_k)/2: λ_k and
    # μ_{k−1} have opposite O(h) errors. At t₀, where μ_{−1} does not exist, the continuous λ(t₀) is
    # reported; at the end one more position stage gives λ_N (its state is discarded, and so is
    # its Newton status: it does not affect the trajectory).
    _, lam_end = _advance(scheme, system, args, constants, h, t0, last)
    later = 0.5 * (mus + jnp.concatenate([lams_first[1:], lam_end[None]]))
    multipliers = jnp.concatenate([lam0[None], later])
    q = jnp.concatenate([q0[None], qs])
    qd = jnp.concatenate([qd0[None], qds])
    t = t0 + h * save_every * jnp.arange(num_saves + 1, dtype=q0.dtype)
    if throw:
        q = compiled_check(q, last.failed_step >= 0, 0, (_FAILURE,))
    stats = dict(
        num_steps=jnp.asarray(num_steps),
        newton_iterations=last.iterations,
        max_newton_iterations=last.max_iterations,
        failed_step=last.failed_step,
        multipliers=multipliers,
    )
    return Trajectory.from_states(
        system, t, q, qd, args, stats=stats, result=diffrax.RESULTS.promote(last.result)
    )


def simulate_variational(
    system: Validated[System],
    q0: Coordinates,
    qd0: Velocities,
    *,
    dt: RealScalarLike,
    num_steps: int,
    t0: RealScalarLike = 0.0,
    args: Args = None,
    save_every: int = 1,
    method: Validated[AbstractVariationalMethod | None] = None,
    order: int = 2,
    newton_rtol: float | None = None,
    newton_atol: float | None = None,
    max_newton_steps: int = 20,
    throw: bool = True,
    checks: Validated[Checks] = Checks(),
) -> Trajectory:
    r"""Integrate ``system`` with a constrained symplectic (variational / RATTLE) integrator.

    A fixed-step sibling of [`simulate`][jaxlag.simulate] for long horizons: the constraints
    ``f(q, t) = 0`` and ``J q̇ + ∂f/∂t = 0`` hold to the Newton tolerance at every step, the energy
    error of a conservative autonomous system stays bounded instead of drifting, and momenta of
    symmetries are conserved to round-off. The equations: [Variational integration][variational-equations].

    **Arguments:**

    - ``system``: a [`System`][jaxlag.System] with optional ``holonomic`` constraints (scleronomic
      or rheonomic), ``dissipation`` and ``forces`` (discrete Lagrange–d'Alembert), and
      time-dependent ``L``. Velocity (Pfaffian) constraints, unilateral constraints and
      ``least_squares=True`` are not supported (``NotImplementedError``).
    - ``q0``, ``qd0``: initial coordinates and velocities on the constraint manifold (see
      [`consistent_initial_state`][jaxlag.consistent_initial_state]).
    - ``dt``: the fixed step ``h`` (traced: a new value does not recompile, and gradients with
      respect to it exist); ``num_steps``: number of steps (static).
    - ``t0``: initial time; ``args``: parameters passed to every user function.
    - ``save_every``: save every this many steps (``num_steps`` must be a multiple); the
      trajectory has ``num_steps // save_every + 1`` states including the initial one. Under
      reverse-mode differentiation each block of ``save_every`` steps is recomputed
      (checkpointed), so memory scales with the number of saves, not of steps.
    - ``method``: [`Rattle`][jaxlag.Rattle] (trapezoidal discrete Lagrangian; ``L`` quadratic in
      ``q̇``), [`VariationalMidpoint`][jaxlag.VariationalMidpoint] (midpoint; any regular ``L``), or ``None``
      (default: ``Rattle()`` when ``L`` is recognisably quadratic in ``q̇``, else
      ``VariationalMidpoint()``).
    - ``order``: 2 (the plain step), 4 or 6: symmetric compositions of it (Yoshida's triple
      jump, and his 7-stage method) of 3 or 7 substeps per step, some of negative size; still
      symplectic, symmetric and constraint-preserving. ``stats["multipliers"]`` stay second
      order; ``traj.multipliers`` (KKT at the saved states) have the order of the states.
    - ``newton_rtol``, ``newton_atol``, ``max_newton_steps``: `optimistix.Newton`
      tolerances (defaults ``1e-12`` in float64, ``1e-5`` in float32) and iteration limit per
      implicit solve. A solve stops when the last correction is below
      ``atol + rtol·|unknown|`` and the residual below ``atol``; the residuals are in the units
      of ``f`` (constraint rows) and of ``M·q`` (momentum rows, multiplied by ``h``), so they
      are meaningful as absolute numbers for problems of order-one scale; rescale otherwise.
    - ``throw``: raise (also under ``jit``) if a step fails; with ``False`` inspect
      ``traj.result`` and ``traj.stats["failed_step"]``.
    - ``checks``: a [`Checks`][jaxlag.Checks], as in [`simulate`][jaxlag.simulate]: ``initial_state``
      and ``constraint_tolerance`` (default 1e-8 in float64, ``√ε`` in float32) apply; there
      are no save times to check (``times`` is ignored). With
      ``compiled=jl.NaNOnFailure()`` a check that fails inside ``jit`` makes ``traj.q`` NaN
      instead of raising (``traj.stats["failed_step"]`` says which step failed), with no host
      callback in the program.

    Returns a [`Trajectory`][jaxlag.Trajectory] whose ``qd`` are the velocities of the discrete
    Legendre transform projected onto ``J q̇ + ∂f/∂t = 0``; its derived quantities (energy,
    momenta, KKT multipliers) are computed from them as usual. ``traj.stats`` holds
    ``multipliers`` (the integrator's discrete multipliers ``(μ_{k−1} + λ_k)/2`` at the saved
    states, ``(T, m_h)``, sign convention ``M q̈ = F + Jᵀλ``, second-order accurate; the KKT
    value at ``t₀``),
    ``newton_iterations`` (total), ``max_newton_iterations`` (per step), ``num_steps`` and
    ``failed_step`` (−1 if none).
    """
    if not isinstance(system, System):
        raise TypeError(f"system must be a jl.System; got {type(system).__name__}.")
    if isinstance(method, str):
        raise TypeError(
            f"method={method!r}: simulate_variational's method is an object now: "
            "method=jl.Rattle(), method=jl.VariationalMidpoint(), or None (the default: chosen "
            "from the structure of L)."
        )
    if method is not None and not isinstance(method, AbstractVariationalMethod):
        raise TypeError(
            f"method must be jl.Rattle(), jl.VariationalMidpoint() or None; got {type(method).__name__}."
        )
    if system.velocity_constraints is not None:
        raise NotImplementedError(
            "simulate_variational supports holonomic constraints only; velocity (Pfaffian, "
            "nonholonomic) constraints need a nonholonomic integrator. Use jl.simulate."
        )
    if system.unilateral:
        raise NotImplementedError(
            "simulate_variational does not handle unilateral constraints (contact switching); "
            "use jl.simulate."
        )
    if system.friction:
        raise NotImplementedError(
            "simulate_variational does not handle Coulomb friction (stick–slip switching); use jl.simulate."
        )
    if system.least_squares:
        raise NotImplementedError(
            "simulate_variational needs independent constraints (its Newton matrix is singular "
            "for redundant ones): remove the redundant rows instead of least_squares=True."
        )
    if order not in COMPOSITIONS:
        raise ValueError(f"order must be one of {tuple(COMPOSITIONS)}; got {order!r}.")
    num_steps = int(num_steps)
    save_every = int(save_every)
    if num_steps < 1 or save_every < 1:
        raise ValueError("num_steps and save_every must be positive integers.")
    if num_steps % save_every:
        raise ValueError(f"num_steps ({num_steps}) must be a multiple of save_every ({save_every}).")
    q0 = jnp.asarray(q0)
    if not jnp.issubdtype(q0.dtype, jnp.floating):
        q0 = q0.astype(jnp.result_type(float))
    qd0 = jnp.asarray(qd0, q0.dtype)
    args = as_array_leaves(args, q0.dtype)
    t0 = jnp.asarray(t0, q0.dtype)
    dt = jnp.asarray(dt, q0.dtype)
    if is_concrete(dt) and not float(dt) > 0:
        raise ValueError(f"dt must be positive; got {float(dt)}.")
    system.check(q0, qd0, t0, args)
    structure = lagrangian_structure(system, q0, qd0, t0, args)
    if method is None:
        method = Rattle() if structure.quadratic else VariationalMidpoint()
    if isinstance(method, Rattle) and not structure.quadratic:
        # The static analysis could not prove it: check numerically at the initial state.
        deviation = _check_quadratic(system, q0, qd0, t0, args)
        if is_concrete(deviation):
            if not float(deviation) <= 1e-8:
                raise ValueError(
                    "method=jl.Rattle() needs a Lagrangian quadratic in q̇ (L = ½ q̇ᵀM(q)q̇ + "
                    "b(q)·q̇ − V(q)); this one is not (third difference in q̇ relative to L: "
                    f"{float(deviation):.3g}). Use method=jl.VariationalMidpoint()."
                )
        else:
            q0 = compiled_check(
                q0,
                ~(deviation <= 1e-8),
                0,
                (
                    "jaxlag.simulate_variational: method=jl.Rattle() needs a Lagrangian quadratic "
                    "in q̇; use method=jl.VariationalMidpoint().",
                ),
            )
            q0 = cast(jax.Array, q0)  # error_if returns its input (typed as any pytree)
        structure = LagrangianStructure(True, False)
    constant_mass = structure.constant_mass and not _has_forces(system)
    default_tolerance = 1e-12 if q0.dtype == jnp.float64 else 1e-5
    scheme = _Scheme(
        rule=method.rule,
        quadratic=structure.quadratic,
        constant_mass=constant_mass,
        constrained=system.holonomic is not None,
        order=order,
        rtol=float(default_tolerance if newton_rtol is None else newton_rtol),
        atol=float(default_tolerance if newton_atol is None else newton_atol),
        max_newton_steps=int(max_newton_steps),
    )
    if not isinstance(checks, Checks):
        raise TypeError(f"checks must be a jl.Checks; got {type(checks).__name__}.")
    constraint_tolerance = checks.tolerance(q0.dtype)
    check_in_jit = checks.initial_state
    concrete = is_concrete((q0, qd0, t0, dt, args))
    if checks.initial_state and is_concrete((q0, qd0, t0, args)):
        q0, qd0 = validate_initial_state(system, q0, qd0, t0, args, constraint_tolerance)
        check_in_jit = False
    with on_failure(checks.compiled):
        traj = _integrate(
            scheme,
            system,
            q0,
            qd0,
            t0,
            dt,
            args,
            num_steps,
            save_every,
            bool(throw) and not concrete,  # eagerly: the host reads the record (no callback)
            check_in_jit,
            float(constraint_tolerance),
        )
    if throw and concrete:
        stats = cast(dict, traj.stats)
        failed_step = int(stats["failed_step"])
        if failed_step >= 0:
            raise SimulationError(
                f"{_FAILURE} (Step {failed_step} failed, at t = {float(t0) + failed_step * float(dt):.10g}.)"
            )
    return traj
