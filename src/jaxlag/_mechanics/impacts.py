r"""Impacts on unilateral constraints: Newton's law of restitution through the KKT structure.

At an impact the velocities jump, ``q̇⁻ → q̇⁺``, by an impulse ``Λ`` on the constraint rows:

    M Δq̇ = Gᵀ Λ,        G q̇⁺ = v*,

with ``G = [J_S; A]`` the holonomic rows of the set ``S`` that takes part and the Pfaffian rows,
and targets (``ḟ = J q̇ + ∂f/∂t``, the rate of a gap; ``g = A q̇ + b``)

* ``ḟ_i⁺ = −e_i ḟ_i⁻`` on the impacting rows ``I`` (Newton's law, restitution ``e_i ∈ [0, 1]``);
* ``ḟ_i⁺ = 0`` on the rows that act already (bilateral ones and unilateral ones in persistent
  contact), ``g⁺ = 0`` on the velocity constraints.

It is the KKT system of `jaxlag._mechanics.kkt.solve_kkt` with ``F = 0``: ``Δq̇`` and ``Λ``
come out of one range-space solve ``(G M⁻¹ Gᵀ) Λ = v* − G q̇⁻``. ``Λ`` has the units of
momentum and the sign of ``λ`` (``Λ_i ≥ 0`` pushes on a unilateral row ``f_i ≥ 0``).

**Simultaneous impacts (the law implemented).** ``I`` holds every inactive unilateral row that
touches (``|f_i| ≤`` the constraint tolerance) and approaches (``ḟ_i⁻ < 0``) at the impact
instant, plus the row whose contact ended the segment; all of ``I`` and the acting rows are
solved together as one KKT system. A unilateral row whose impulse would pull (``Λ_i < 0``) is
dropped from ``S`` (it separates) and the system is solved again, the most negative first, until
no row pulls. With one impacting row this is exact Newton's law; with several it is the
simultaneous (rigid, "all rows at once") law, which for ``e = 1`` and a chain of touching bodies
moves the touching bodies as one (not the sequential Newton's-cradle answer: leave gaps between
the bodies for that).

**After the impact.** An impacting row with ``e_i > 0`` rebounds (``ḟ_i⁺ = e_i |ḟ_i⁻| > 0``):
it stays inactive and the body leaves. A row with ``e_i = 0`` engages (persistent contact), and
so does one that ends an accumulation of impacts (below).

**Zeno (accumulation of impacts).** A body pressed onto a constraint (normal acceleration
``f̈_i < 0`` with the rows acting before the impact) that rebounds with ``ḟ_i⁺ = e_i |ḟ_i⁻|`` is
back after the flight time ``τ_i = 2 e_i |ḟ_i⁻| / |f̈_i|`` (exact for a constant ``f̈``: a ball
bouncing under gravity), having risen by ``(e_i ḟ_i⁻)² / (2|f̈_i|)``; the flights shrink
geometrically and infinitely many impacts accumulate in finite time. An impact that ends the
accumulation (`ends_accumulation`: by default, a rise within the constraint tolerance; with
``Events(zeno_time=τ)``, a flight shorter than ``τ``) is plastic (``e_i → 0``) and the contact
persists, after which the multiplier carries the load (``λ = m g`` for a ball at rest). Bodies
not pressed onto the constraint (``f̈_i ≥ 0``) never count as Zeno.

**The coefficients are checked where they are used.** ``e_i`` must lie in ``[0, 1]``: a
concrete value is refused when the `Unilateral` is built; a traced one (``jit``, ``vmap``,
``grad``) by the segment loop before the first step (`bad_restitution`,
``FailureCode.RESTITUTION``): ``e > 1`` would add energy at every impact and ``e < 0`` let the
body pass into the constraint, and ``jax.grad`` would differentiate that motion as if it
were one.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._custom_types import RealArrayLike, Validated
from .constraints import holonomic_terms, velocity_terms
from .kkt import accelerations_and_multipliers, solve_kkt
from .lagrangian import mass_solver


class Unilateral(eqx.Module):
    r"""One-sided holonomic constraints ``f_i(q, t) ≥ 0`` and their impact law:
    ``System(..., unilateral=jl.Unilateral(indices, restitution=e))``.

    - ``indices``: which holonomic constraints are one-sided (an int or a sequence of ints;
      ``unilateral=indices`` on [`System`][jaxlag.System] is ``Unilateral(indices)``, plastic).
    - ``restitution``: Newton's coefficient ``e ∈ [0, 1]``, one value for all of them or one per
      index (in the order of ``indices``). At an impact the approach rate ``ḟ_i⁻ < 0`` becomes
      ``ḟ_i⁺ = −e_i ḟ_i⁻``; ``e = 0`` (the default) is perfectly plastic (the contact engages),
      ``e = 1`` perfectly elastic. It is an array leaf: ``jax.grad`` and ``jax.vmap`` flow
      through it (build the system inside the function you transform).

    **The impact law.** At an impact the velocities jump by an impulse ``Λ`` on the constraint
    rows, solved through the KKT structure ([`simulate`][jaxlag.simulate]'s ``M q̈ = F + Jᵀλ + Aᵀμ``
    with ``F = 0`` and velocities for accelerations)::

        M (q̇⁺ − q̇⁻) = J_Sᵀ Λ (+ Aᵀ·),    ḟ_i⁺ = −e_i ḟ_i⁻ (impacting),  ḟ_i⁺ = 0 (acting),  g⁺ = 0

    (``ḟ = J q̇ + ∂f/∂t``; ``Λ`` in momentum units, ``Λ_i ≥ 0`` pushes). *Simultaneous
    impacts:* the impacting set is every inactive one-sided row that touches (``|f_i| ≤`` the
    constraint tolerance) and approaches (``ḟ_i⁻ < 0``) at the instant; all of them and the
    rows already acting are solved together as one KKT system. A one-sided row whose impulse
    would pull (``Λ_i < 0``) is dropped (it separates) and the rest solved again, the most
    negative first, until none pulls. With one impacting row this is exactly Newton's law; for
    bodies already touching in a chain it moves them as one (leave gaps between the balls of a
    Newton's cradle for the sequential answer). *After the impact* a row with ``e_i > 0``
    rebounds and stays inactive (the body leaves); one with ``e_i = 0`` engages.

    **Zeno.** A body pressed onto the constraint (normal acceleration ``f̈_i < 0`` with the
    rows acting before the impact) would rise by ``(e_i ḟ_i⁻)² / (2|f̈_i|)`` and fly
    ``τ = 2 e_i |ḟ_i⁻| / |f̈_i|`` after the rebound. When the rise is within the constraint
    tolerance (the default), or ``τ`` is below [`Events`][jaxlag.Events]' ``zeno_time`` if one
    is given, the impact is plastic and the contact persists: a bouncing ball comes to rest
    and the multiplier carries its weight. The impulses are recorded in
    ``traj.events.impulses`` ([`EventLog`][jaxlag.EventLog]); rebounds are ``IMPACT`` entries
    of the log, the plastic impacts ``CONTACT`` ones.

    ``restitution`` traced through ``jit``, ``vmap`` or ``grad`` cannot be checked here: a
    value outside ``[0, 1]`` or NaN stops the simulation before its first step
    (``jl.FailureCode.RESTITUTION``, a ``SimulationError`` naming it).
    """

    indices: tuple[int, ...] = eqx.field(static=True)
    restitution: Float[Array, " k"]

    def __init__(self, indices: Validated[int | Sequence[int]], restitution: Validated[RealArrayLike] = 0.0):
        if isinstance(indices, (int, np.integer)) and not isinstance(indices, bool):
            indices = (int(indices),)
        try:
            given = [int(i) for i in indices]  # pyright: ignore[reportGeneralTypeIssues]
        except TypeError as error:
            raise TypeError(
                f"Unilateral indices must be an int or a sequence of ints; got {indices!r}."
            ) from error
        if len(set(given)) != len(given) or any(i < 0 for i in given):
            raise ValueError(f"Unilateral indices must be distinct non-negative ints; got {given}.")
        k = len(given)
        try:
            host = np.asarray(restitution)  # a traced value (under jit, vmap, grad) is checked by shape only
        except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
            host = None
        shape = np.shape(restitution) if host is None else host.shape
        if len(shape) > 1 or (len(shape) == 1 and shape[0] != k):
            raise ValueError(
                f"restitution must be a scalar or have one entry per index ({k}); got shape {shape}."
            )
        if host is not None:
            if not np.issubdtype(host.dtype, np.number) or np.any(~np.isfinite(host)):
                raise ValueError(f"restitution must be finite numbers in [0, 1]; got {restitution!r}.")
            if np.any((host < 0) | (host > 1)):
                raise ValueError(
                    f"restitution must lie in [0, 1] (0 plastic, 1 elastic); got {restitution!r}."
                )
        if isinstance(restitution, jax.Array):
            values = jnp.broadcast_to(restitution, (k,))
        else:
            assert host is not None
            dtype = jax.dtypes.canonicalize_dtype(host.dtype if host.dtype.kind == "f" else float)
            values = jax.device_put(np.broadcast_to(host, (k,)).astype(dtype))
        order = np.argsort(given, kind="stable")
        self.indices = tuple(given[i] for i in order)
        self.restitution = values if k == 0 or np.all(np.diff(order) > 0) else values[order]


def as_unilateral(unilateral: int | Sequence[int] | Unilateral) -> Unilateral:
    """``System``'s ``unilateral=``: a `Unilateral`, or indices (plastic)."""
    if isinstance(unilateral, Unilateral):
        return unilateral
    if isinstance(unilateral, (bool, np.bool_)):
        raise TypeError(
            f"unilateral={unilateral!r}: give the indices of the one-sided holonomic rows "
            "(an int or a sequence of ints), or jl.Unilateral(indices, restitution=e)."
        )
    if isinstance(unilateral, (int, np.integer)):
        return Unilateral((int(unilateral),))
    return Unilateral(tuple(sorted({int(i) for i in unilateral})))  # repeated indices: once


def restitution_rows(system, m_h: int, dtype) -> Array:
    """``e_i`` per holonomic row (m_h,): 0 for bilateral rows and plastic systems."""
    law = getattr(system, "unilateral_law", None)
    e = jnp.zeros((m_h,), dtype)
    if law is None or not law.indices:
        return e
    return e.at[jnp.asarray(law.indices)].set(jnp.asarray(law.restitution).astype(dtype))


def bad_restitution(system, m_h: int, dtype) -> tuple[Bool[Array, ""], Array, Array]:
    """``(bad, position, e)``: whether a coefficient of restitution is outside ``[0, 1]`` or
    not finite, and the first such one (its position in ``Unilateral.indices`` and its value).
    In the program: a traced ``e`` was not checked when the `Unilateral` was built."""
    law = getattr(system, "unilateral_law", None)
    if law is None or not law.indices:
        return jnp.asarray(False), jnp.asarray(-1, jnp.int32), jnp.asarray(jnp.nan, dtype)
    e = jnp.asarray(law.restitution).astype(dtype)
    wrong = ~(jnp.isfinite(e) & (e >= 0) & (e <= 1))
    first = jnp.argmax(wrong)
    return jnp.any(wrong), first.astype(jnp.int32), e[first]


def ends_accumulation(rebound, f_ddot, zeno_time: float | None, tolerance):
    r"""Whether an impact whose rebound rate would be ``rebound = e |ḟ⁻| ≥ 0``, under the
    normal acceleration ``f̈``, ends an accumulation of impacts (and is therefore plastic).

    Only a body pressed onto the constraint (``f̈ < 0``) accumulates impacts: it would fly
    ``τ = 2 rebound / |f̈|`` and rise by ``rebound² / (2|f̈|)``. With ``zeno_time`` ``None`` the
    impact is plastic when the rise is within the constraint ``tolerance``: the body would not
    leave the band in which a constraint counts as touching (``|f| ≤ tolerance``), so nothing
    the run resolves is lost, and the rule depends on this impact alone, not on the time
    span or the save times. With a ``zeno_time``: when ``τ < zeno_time``. Written without
    divisions (``f̈ = 0`` is no accumulation)."""
    pressed = f_ddot < 0
    if zeno_time is None:
        return pressed & (rebound * rebound <= 2.0 * tolerance * -f_ddot)
    return pressed & (2.0 * rebound < -f_ddot * zeno_time)


def impacts_to_rest(
    system, q, qd, t, t1, args, active, unilateral, zeno_time: float | None, tolerance
) -> tuple[Array, Array]:
    r"""``(impacts, row)`` at a state just after a rebound: how many more impacts the
    accumulation of impacts on a unilateral row needs until one ends it (`ends_accumulation`)
    or until ``t1``, by the geometric series, and which row (NaN and −1 if no row accumulates).

    A row rebounding (inactive, touching, ``ḟ = v > 0``) under a constant pressing ``f̈ = −a``
    with restitution ``0 < e < 1`` lands after ``2v/a``; its j-th next impact approaches at
    ``v e^(j−1)`` and would rebound at ``v e^j``, after flights summing to
    ``(2v/a)(1 − e^j)/(1 − e)``. The accumulation ends at the first ``j`` with
    ``(v e^j)² ≤ 2 tol a`` (``2 v e^j / a < zeno_time``), or the run at ``t1`` after the ``j``
    with ``(2v/a)(1 − e^j)/(1 − e) ≤ t1 − t``. For the advice of ``FailureCode.MAX_SEGMENTS``:
    counting the segments at the rate so far extrapolates linearly and undercounts a geometric
    sequence by orders of magnitude."""
    m_h = active.shape[0]
    dtype = q.dtype
    e = restitution_rows(system, m_h, dtype)
    f, f_dot, jac, gamma = holonomic_terms(system, q, qd, t, args)
    qdd = accelerations_and_multipliers(system, q, qd, t, args, active=active)[0]
    a = -(jac @ qdd + gamma)
    v = f_dot
    bouncing = unilateral & ~active & (jnp.abs(f) <= tolerance) & (v > 0) & (a > 0) & (e > 0) & (e < 1)
    safe_e = jnp.where(bouncing, e, 0.5)
    safe_v = jnp.where(bouncing, v, 1.0)
    safe_a = jnp.where(bouncing, a, 1.0)
    log_e = jnp.log(safe_e)
    if zeno_time is None:
        to_rest = jnp.log(2.0 * tolerance * safe_a / safe_v**2) / (2.0 * log_e)
    else:
        to_rest = jnp.log(zeno_time * safe_a / (2.0 * safe_v)) / log_e
    to_rest = jnp.maximum(jnp.ceil(to_rest), 1.0)
    flight = 2.0 * safe_v / safe_a
    left = 1.0 - (jnp.asarray(t1, dtype) - t) * (1.0 - safe_e) / flight
    to_end = jnp.where(left > 0, jnp.floor(jnp.log(jnp.where(left > 0, left, 1.0)) / log_e), jnp.inf)
    impacts = jnp.where(bouncing, jnp.minimum(to_rest, to_end), -jnp.inf)
    row = jnp.argmax(impacts)
    found = jnp.any(bouncing)
    return jnp.where(found, impacts[row], jnp.nan), jnp.where(found, row, -1).astype(jnp.int32)


def impact(
    system,
    q,
    qd,
    t,
    args,
    active: Bool[Array, " m_h"],
    unilateral: Bool[Array, " m_h"],
    forced: Bool[Array, " m_h"],
    excluded: Bool[Array, " m_h"],
    zeno_time,
    tolerance,
):
    r"""The impact at ``(q, q̇⁻)``: ``(q̇⁺, Λ (m_h,), active after, rebounding rows)``.

    ``active``: the rows acting before the impact; ``forced``: rows that impact whatever their
    gap (the contact that ended the segment); ``excluded``: rows that must not impact (one just
    released); ``zeno_time``: ``Events.zeno_time`` (``None``: the default rule of
    `ends_accumulation`). Other inactive unilateral rows impact when they touch (``f_i ≤ tolerance``) and
    approach (``ḟ_i < 0``), or are violated (``f_i < −tolerance``, after a user's reset). With
    no impacting row this is the velocity projection onto the acting rows (``Λ ≈ 0`` when the
    state is consistent). See the module docstring for the law.
    """
    m_h = active.shape[0]
    dtype = q.dtype
    e = restitution_rows(system, m_h, dtype)
    f, f_dot, jac, gamma = holonomic_terms(system, q, qd, t, args)
    impacting = forced | (
        unilateral & ~active & ~excluded & (f <= tolerance) & ((f_dot < 0) | (f < -tolerance))
    )
    # Normal acceleration with the rows acting before the impact: f̈ = J q̈ + γ.
    qdd = accelerations_and_multipliers(system, q, qd, t, args, active=active)[0]
    f_ddot = jac @ qdd + gamma
    # Zeno: the rebound would end an accumulation of impacts; it is plastic.
    e = jnp.where(ends_accumulation(e * jnp.abs(f_dot), f_ddot, zeno_time, tolerance), 0.0, e)
    target = jnp.where(impacting, -e * f_dot, 0.0)  # ḟ⁺ on the rows of S
    rows, change = jac, target - f_dot
    if system.velocity_constraints is not None:
        g, a, _ = velocity_terms(system, q, qd, t, args)
        rows = jnp.concatenate([rows, a])
        change = jnp.concatenate([change, -g])
    solve_mass = mass_solver(system, q, qd, t, args)
    zero_force = jnp.zeros_like(qd)
    ones_v = jnp.ones((rows.shape[0] - m_h,), dtype)

    def solve(mask):
        weights = jnp.concatenate([mask.astype(dtype), ones_v])
        return solve_kkt(
            solve_mass, zero_force, rows, change, least_squares=system.least_squares, active=weights
        )

    in_set = active | impacting
    eps = jnp.finfo(dtype).eps
    for _ in range(len(system.unilateral)):
        _, lam = solve(in_set)
        lam_h = lam[:m_h]
        scale = jnp.max(jnp.abs(lam_h), initial=0.0)
        pulls = in_set & unilateral & (lam_h < -jnp.sqrt(eps) * scale)
        worst = jnp.argmin(jnp.where(pulls, lam_h, jnp.inf))
        in_set = jnp.where(jnp.any(pulls), in_set.at[worst].set(False), in_set)
    delta, lam = solve(in_set)
    rebound = in_set & impacting & (e > 0)
    after = in_set & ~rebound
    impulses = jnp.where(in_set, lam[:m_h], 0.0)
    return qd + delta, impulses, after, rebound
