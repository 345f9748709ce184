r"""Coulomb friction on a contact as a stick–slip element (planar: one tangent direction).

A frictional contact ``j`` pairs a holonomic row ``c_j`` (the normal, ``f_{c_j}(q, t) = 0`` while
it acts, multiplier ``λ_N = λ_{c_j} ≥ 0`` pushing) with a tangential coordinate ``τ_j(q, t)``
whose rate ``v_t = τ̇_j = T_j q̇ + ∂τ_j/∂t`` (``T_j = ∂τ_j/∂q``) is the slip velocity. With
friction coefficient ``μ_j`` the tangential generalized force is ``T_jᵀ λ_t``:

* **slip** (mode ``s = ±1``, the sign of ``v_t``, fixed for a segment):
  ``λ_t = −μ s λ_N``, i.e. ``M q̈ = F + Jᵀλ + Aᵀμ + (J_{c} − μ s T)ᵀ λ_N``. The KKT system
  is no longer symmetric: with ``G`` the constraint rows and ``Ĝ`` the same rows with
  ``J_c → J_c − μ s T`` on the force side, ``X = M⁻¹[F, Ĝᵀ]``, ``S = G M⁻¹ Ĝᵀ`` (m × m,
  solved by LU) and ``S Λ = c − G M⁻¹F``;
* **stick** (mode 0): the velocity row ``v_t = 0`` is added, at the acceleration level
  ``T q̈ = −γ_t`` (``γ_t = d/ds τ̇(q + s q̇, t + s)`` at 0, one nested ``jvp``, as for ``f``), with
  its multiplier ``λ_t``; it holds while ``|λ_t| ≤ μ λ_N``.

The switches are events of the segmented integration (`jaxlag._events`): ``s v_t`` reaching
0 (slip ends: the contact sticks if it can, otherwise slips the other way, ``s = −sign λ_t``)
and ``μ λ_N − |λ_t|`` reaching 0 (stick ends: slip with ``s = −sign λ_t``, so that friction
opposes the impending motion). A contact whose normal row does not act has no friction.
Impacts are frictionless (the tangential velocity is whatever the normal impulse leaves).

**Friction cone (3-D, designed, not implemented).** Two tangent rows ``T = [T_1; T_2]`` per
contact: stick adds both rows and holds while ``‖λ_t‖ ≤ μ λ_N``; slip applies
``λ_t = −μ λ_N u`` along a unit direction ``u = v_t / ‖v_t‖`` — not fixed in a segment, so either
``u`` is re-evaluated from the state in the vector field (the slip force is then ``−μ λ_N
v_t/‖v_t‖``, smooth while ``‖v_t‖ > 0``, with the event ``‖v_t‖ → 0``; the KKT stays linear
in ``λ`` since ``u`` depends on the state only), or the cone is replaced by a polygon of
``p`` edge directions, each slip segment having one fixed edge, like the planar ``s``.
"""

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._conventions import UserFunction, wrap_configuration_function
from .._custom_types import RealScalarLike, Validated
from .constraints import constraint_rows, holonomic_terms, velocity_terms
from .kkt import accelerations_and_multipliers, solve_kkt
from .lagrangian import as_time, mass_solver, mass_solver_and_forces
from .mass_solve import Factorization, nan_unless


class Coulomb(eqx.Module):
    r"""Coulomb friction on a contact, as a stick–slip element:
    ``System(..., friction=jl.Coulomb(contact, tangent, mu))``.

    - ``contact``: the index of the holonomic row that is the contact's normal, ``f_c(q, t)``
      (a unilateral row, ``System(..., unilateral=...)``), written so that its multiplier
      ``λ_N = λ_c ≥ 0`` pushes (``f_c ≥ 0`` outside the body). A bilateral row is refused: its
      multiplier may change sign, and ``μ λ_N`` is then no friction bound.
    - ``tangent``: ``τ(q, [t], [args]) -> scalar``, a tangential coordinate of the contact point
      whose time derivative is the slip velocity ``v_t = τ̇ = T q̇ + ∂τ/∂t`` (``T = ∂τ/∂q``);
      e.g. the distance along a ramp ``cos θ x + sin θ y``, or ``x − R φ`` for a rolling disc.
    - ``mu``: the friction coefficient ``μ ≥ 0`` (one value for sliding and sticking). An array
      leaf: ``jax.grad`` and ``jax.vmap`` flow through it (build the system inside the
      function you transform). A concrete ``mu`` is checked here; a traced one (``jit``,
      ``vmap``, ``grad``) that is negative or NaN stops the simulation before its first step
      (``jl.FailureCode.FRICTION_COEFFICIENT``, a ``SimulationError`` naming it).

    The tangential generalized force is ``Tᵀλ_t``: while slipping with ``s = sign v_t``,
    ``λ_t = −μ s λ_N``; while sticking, ``λ_t`` is the multiplier of the added row ``v_t = 0``,
    held while ``|λ_t| ≤ μ λ_N``. [`simulate`][jaxlag.simulate] integrates in segments with the
    mode of each contact fixed and switches at the events ``v_t → 0`` ("stick", or a reversed
    "slip" if ``|λ_t| > μ λ_N`` there) and ``|λ_t| → μ λ_N`` ("slip", in the direction the
    net force drives: ``s = −sign λ_t``); [`EventLog`][jaxlag.EventLog] records them, and
    ``traj.friction_forces`` / ``traj.friction_modes`` give ``λ_t`` and the mode. The
    equations, with a worked example: [Friction: stick and slip][friction-stick-and-slip].

    Friction needs the mode, so it lives in [`simulate`][jaxlag.simulate] (and ``simulate_batch``
    with ``jl.Vmap()``); the state methods of [`System`][jaxlag.System] (``accelerations``,
    ``multipliers``) and [`jaxlag.analysis.linearize`][jaxlag.analysis.linearize] give the frictionless
    equations.
    Impacts are frictionless.

    **Step size while sticking.** A stuck body may not move at all: the step-size controller
    then sees no error and takes long steps, and (as for any event condition) a force that
    rises above ``μ λ_N`` and falls back within one step is not seen; a missed pair of
    crossings can also leave the root find without a root (``SimulationError``: "maximum
    number of steps ... nonlinear solver"). Bound the step below the time scale of the forcing:
    ``stepsize_controller=diffrax.PIDController(rtol=..., atol=..., dtmax=...)``.
    """

    contact: int = eqx.field(static=True)
    tangent: UserFunction
    mu: Float[Array, ""]

    def __init__(self, contact: Validated[int], tangent: Validated[Callable], mu: Validated[RealScalarLike]):
        if isinstance(contact, bool) or not isinstance(contact, (int, np.integer)) or contact < 0:
            raise TypeError(f"Coulomb contact must be a non-negative int (a holonomic row); got {contact!r}.")
        if not callable(tangent):
            raise TypeError(f"Coulomb tangent must be a function tau(q, [t], [args]); got {tangent!r}.")
        try:
            host = np.asarray(mu)  # a traced value (under jit, vmap, grad) is checked by shape only
        except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
            host = None
        if np.shape(mu) != ():
            raise ValueError(f"Coulomb mu must be a scalar; got shape {np.shape(mu)}.")
        if host is not None:
            if not np.issubdtype(host.dtype, np.number) or not np.isfinite(host) or host < 0:
                raise ValueError(f"Coulomb mu must be a finite number ≥ 0; got {mu!r}.")
        self.contact = int(contact)
        self.tangent = wrap_configuration_function(tangent, "Coulomb tangent function")
        if isinstance(mu, jax.Array):
            self.mu = mu
        else:
            assert host is not None
            dtype = jax.dtypes.canonicalize_dtype(host.dtype if host.dtype.kind == "f" else float)
            self.mu = jax.device_put(host.astype(dtype))


def as_friction(friction: Coulomb | Sequence[Coulomb] | None) -> tuple[Coulomb, ...]:
    """``System``'s ``friction=``: one `Coulomb`, a sequence of them, or ``None``."""
    if friction is None:
        return ()
    elements = (friction,) if isinstance(friction, Coulomb) else tuple(friction)
    for element in elements:
        if not isinstance(element, Coulomb):
            raise TypeError(f"friction takes jl.Coulomb elements; got {type(element).__name__}.")
    contacts = [e.contact for e in elements]
    if len(set(contacts)) != len(contacts):
        raise ValueError(f"Each contact has at most one jl.Coulomb element; got contacts {contacts}.")
    return elements


# --------------------------------------------------------------------------- tangent terms
def tangent_terms(system, q, qd, t, args):
    """``(τ, v_t, T, γ_t)`` (k,), (k,), (k, n), (k,) of the frictional contacts at a state."""
    t = as_time(t, q)

    def tau(x, s):
        return jnp.stack([jnp.asarray(e.tangent(x, t=s, args=args), q.dtype) for e in system.friction])

    def along_motion(s):
        return tau(q + s * qd, t + s)

    def first_derivative(s):
        return jax.jvp(along_motion, (s,), (jnp.ones_like(s),))

    zero = jnp.zeros((), t.dtype)
    (value, rate), (_, gamma) = jax.jvp(first_derivative, (zero,), (jnp.ones_like(zero),))
    jac = jax.jacrev(lambda x: tau(x, t))(q)
    return value, rate, jac, gamma


def _contact_data(system, m_h: int, dtype):
    """``(μ (k,), E (k, m_h))``: coefficients and the one-hot map contact → normal row."""
    mu = jnp.stack([jnp.asarray(e.mu, dtype) for e in system.friction])
    rows = np.zeros((len(system.friction), m_h))
    for j, e in enumerate(system.friction):
        rows[j, e.contact] = 1.0
    return mu, jnp.asarray(rows, dtype)


def bad_friction_coefficient(system, dtype) -> tuple[Bool[Array, ""], Array, Array]:
    """``(bad, position, μ)``: whether a friction coefficient is negative or not finite, and the
    first such contact (its position in ``System.friction``) and its ``μ``. In the program: a
    traced ``μ`` was not checked when the `Coulomb` was built, and ``μ < 0`` would make
    friction drive the slip (a block pushed up the slope by it)."""
    if not system.friction:
        return jnp.asarray(False), jnp.asarray(-1, jnp.int32), jnp.asarray(jnp.nan, dtype)
    mu = jnp.stack([jnp.asarray(e.mu, dtype) for e in system.friction])
    wrong = ~(jnp.isfinite(mu) & (mu >= 0))
    first = jnp.argmax(wrong)
    return jnp.any(wrong), first.astype(jnp.int32), mu[first]


def friction_count(system) -> int:
    return len(getattr(system, "friction", ()))


def solve_with_modes(system, q, qd, t, args, baumgarte=None, active=None, modes=None):
    r"""``(q̈, λ, μ, λ_t)`` of ``M q̈ = F + Jᵀλ + Aᵀμ + Tᵀλ_t`` with each contact in its mode.

    ``modes`` (k,): 0 stick, ``±1`` slip with ``sign v_t = ±1``; a contact whose normal row is
    inactive (``active``) has no friction (``λ_t = 0``). Without friction (or ``modes`` None)
    this is `accelerations_and_multipliers` with ``λ_t`` empty or 0.
    """
    k = friction_count(system)
    if k == 0 or modes is None:
        qdd, lam, mu_v = accelerations_and_multipliers(system, q, qd, t, args, baumgarte, active)
        return qdd, lam, mu_v, jnp.zeros((k,), q.dtype)
    dtype = q.dtype
    m_h = system.num_holonomic(q, t, args)
    solve_mass, force = mass_solver_and_forces(system, q, qd, t, args)
    rows, rhs = constraint_rows(system, q, qd, t, args, baumgarte)
    m = rows.shape[0]
    weight_h = jnp.ones((m_h,), dtype) if active is None else jnp.asarray(active, dtype)
    coefficient, to_normal = _contact_data(system, m_h, dtype)
    acting = to_normal @ weight_h  # (k,) 1 where the contact's normal row acts
    modes = jnp.asarray(modes, dtype)
    stick = acting * (modes == 0).astype(dtype)
    slip = acting * coefficient * modes  # μ s on the acting slipping contacts
    _, _, tangent_rows, gamma_t = tangent_terms(system, q, qd, t, args)
    weight = jnp.concatenate([weight_h, jnp.ones((m - m_h,), dtype), stick])
    g = jnp.concatenate([rows, tangent_rows]) * weight[:, None]
    c = jnp.concatenate([rhs, -gamma_t]) * weight
    # Force side: the normal column J_c becomes J_c − μ s T on a slipping contact.
    slip_columns = to_normal.T @ (slip[:, None] * tangent_rows)  # (m_h, n)
    g_force = g - jnp.concatenate([slip_columns, jnp.zeros((m - m_h + k, q.shape[0]), dtype)])
    factored = solve_mass if isinstance(solve_mass, Factorization) else None
    finite_solve: Any = factored.finite if factored is not None else solve_mass
    ok = factored.ok if factored is not None else jnp.asarray(True)
    solved = finite_solve(jnp.concatenate([force[:, None], g_force.T], axis=1))
    free, minv_gt = solved[:, 0], solved[:, 1:]
    schur = g @ minv_gt + jnp.diag(1.0 - weight)
    multipliers = jnp.linalg.solve(schur, c - g @ free)
    # A singular frictional KKT matrix (redundant contact rows, or a slip system with no
    # solution at a large μ) makes the solve non-finite: the state fails, as a failed M does.
    ok = ok & jnp.all(jnp.isfinite(multipliers))
    multipliers = jnp.where(jnp.isfinite(multipliers), multipliers, 0.0)
    qdd = free + minv_gt @ multipliers
    lam = multipliers[:m_h]
    lam_t = jnp.where(stick > 0, multipliers[m:], -slip * (to_normal @ lam))
    return (
        nan_unless(ok, qdd),
        nan_unless(ok, lam),
        nan_unless(ok, multipliers[m_h:m]),
        nan_unless(ok, lam_t),
    )


def switch_values(system, q, qd, t, args, active, modes):
    """Per contact, the quantity whose zero ends the segment: ``s v_t`` while slipping,
    ``μ λ_N − |λ_t|`` while sticking, ``inf`` where the normal row does not act."""
    dtype = q.dtype
    m_h = system.num_holonomic(q, t, args)
    coefficient, to_normal = _contact_data(system, m_h, dtype)
    _, lam, _, lam_t = solve_with_modes(system, q, qd, t, args, active=active, modes=modes)
    v_t = tangent_terms(system, q, qd, t, args)[1]
    acting = (to_normal @ jnp.asarray(active, dtype)) > 0
    modes = jnp.asarray(modes, dtype)
    value = jnp.where(modes == 0, coefficient * (to_normal @ lam) - jnp.abs(lam_t), modes * v_t)
    return jnp.where(acting, value, jnp.inf)


def decide_modes(system, q, qd, t, args, active, candidates, directions):
    """The modes at a switch: the ``candidates`` (k,) stick unless that needs
    ``|λ_t| > μ λ_N``; then (the largest excess first, one at a time, re-solving) the contact
    slips in the direction the net force drives, ``s = −sign λ_t``. The others slip along
    ``directions`` (±1). Exact for one contact; for several, the usual heuristic of an LCP."""
    dtype = q.dtype
    k = friction_count(system)
    m_h = system.num_holonomic(q, t, args)
    coefficient, to_normal = _contact_data(system, m_h, dtype)
    modes = jnp.where(candidates, 0.0, jnp.where(directions < 0, -1.0, 1.0)).astype(dtype)
    eps = jnp.finfo(dtype).eps
    for _ in range(k):
        _, lam, _, lam_t = solve_with_modes(system, q, qd, t, args, active=active, modes=modes)
        limit = coefficient * (to_normal @ lam)
        scale = jnp.maximum(jnp.max(jnp.abs(lam), initial=0.0), jnp.max(jnp.abs(lam_t), initial=0.0))
        excess = jnp.abs(lam_t) - limit
        fails = (modes == 0) & (excess > jnp.sqrt(eps) * scale)
        worst = jnp.argmax(jnp.where(fails, excess, -jnp.inf))
        flipped = modes.at[worst].set(jnp.where(lam_t[worst] > 0, -1.0, 1.0))
        modes = jnp.where(jnp.any(fails), flipped, modes)
    return modes


def project_tangent_velocity(system, q, qd, t, args, active, zero):
    r"""Mass-weighted projection of ``q̇`` onto ``ḟ = 0`` (acting holonomic rows), ``g = 0``
    (velocity constraints) and ``v_t = 0`` on the contacts in ``zero`` (k,): at the start of a
    stick (and of a slip from rest) ``v_t`` is exactly 0 instead of the root finder's residual.
    ``M Δq̇ = Gᵀ Λ``, ``G (q̇ + Δq̇) = target``, one KKT solve with ``F = 0``."""
    dtype = q.dtype
    m_h = system.num_holonomic(q, t, args)
    _, v_t, tangent_rows, _ = tangent_terms(system, q, qd, t, args)
    rows_list, change_list, weights = [tangent_rows], [-v_t], [jnp.asarray(zero, dtype)]
    if system.holonomic is not None:
        _, f_dot, jac, _ = holonomic_terms(system, q, qd, t, args)
        rows_list.insert(0, jac)
        change_list.insert(0, -f_dot)
        weights.insert(0, jnp.asarray(active, dtype))
    if system.velocity_constraints is not None:
        g, a, _ = velocity_terms(system, q, qd, t, args)
        rows_list.insert(len(rows_list) - 1, a)
        change_list.insert(len(change_list) - 1, -g)
        weights.insert(len(weights) - 1, jnp.ones((g.shape[0],), dtype))
    del m_h
    delta, _ = solve_kkt(
        mass_solver(system, q, qd, t, args),
        jnp.zeros_like(qd),
        jnp.concatenate(rows_list),
        jnp.concatenate(change_list),
        least_squares=system.least_squares,
        active=jnp.concatenate(weights),
    )
    return qd + delta
