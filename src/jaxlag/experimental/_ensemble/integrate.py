r"""One loop for a whole ensemble: batched explicit Runge–Kutta with the batch as an array axis.

``simulate_batch(..., method=jl.Vmap())`` is ``jax.vmap`` of ``diffrax.diffeqsolve``: every member
runs diffrax's solver loop, and ``vmap`` turns the loop into a batched ``while_loop`` whose body
is the whole of diffrax's step machinery. On an accelerator each iteration launches dozens of small
kernels. Here the state of all ``B`` members is one array pair ``q, q̇`` of shape ``(B, n)``
advanced by **one** loop whose body is one explicit Runge–Kutta step of the batch:

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),   y₁ = y + h Σ b_i k_i,   e = h Σ b̂_i k_i

with ``f(t, (q, q̇)) = (q̇, q̈)`` the library's own equations of motion
([`EquationsOfMotion`][jaxlag.EquationsOfMotion]: ``M q̈ = F + Jᵀλ + Aᵀμ`` by the range-space KKT solve)
``jax.vmap``-ed over the batch axis inside the body, and ``(c, a, b, b̂)`` the Butcher tableau of
the diffrax solver passed as ``solver=`` (``diffrax.Tsit5().tableau``, ...; [`RK4`][jaxlag.RK4] is the
classic fourth-order method as a diffrax solver). Constrained systems are projected onto the
manifold after every accepted step with the same [`Projection`][jaxlag.Projection] as ``simulate``.

**Constant steps** (``diffrax.ConstantStepSize()`` and ``dt0``): save interval ``k`` of member
``b`` is divided into ``m = ceil((t_{k+1} − t_k)/dt0)`` equal steps, so the last step lands
exactly on the save time (the steps are ``dt0`` wherever ``dt0`` divides the intervals). The loop
is a ``lax.scan`` over save intervals around a ``lax.scan`` over steps whose body is
``jax.checkpoint``-ed: forward mode (``jax.jvp``/``jacfwd``) differentiates it directly, reverse
mode stores one state per step and recomputes the stages.

**Adaptive steps** (``diffrax.PIDController``): every member has its own ``t`` and step size
``h``; steps are clipped to land on the member's next save time. The error of a step is diffrax's:
``‖e / (atol + rtol max(|y|, |y₁|))‖_RMS`` over the ``2n`` state entries, accepted when ``< 1``;
the next step is ``h · clip(safety · ε₁^{-β₁/p} ε₀^{-β₂/p} ε₋₁^{-β₃/p}, factormin, factormax)``
with ``β = (pcoeff + icoeff + dcoeff, −(pcoeff + 2 dcoeff), dcoeff)`` and ``p`` the solver's error
order (after a step clipped onto a save time the unclipped proposal is kept). Finished members
are masked; the loop stops when every member has reached its last save time or failed: a member
whose step is rejected at round-off size (``≤ 64 ε max(|t|, t₁ − t₀)``) stops there, as
``jl.simulate``'s guard stops diffrax (non-finite trial state: code 1; finite: the step size
collapsed, code 5). `member_failures` turns how each member ended into the
`Failure` record of ``jl.simulate`` (a non-finite save also fails the
member: constant steps cannot shrink), with the unreached saves ``inf``. The loop is
``equinox.internal.while_loop``: ``kind="checkpointed"`` (reverse mode, memory ``O(log steps)``)
with the default ``adjoint=diffrax.RecursiveCheckpointAdjoint()``, ``kind="lax"`` (forward mode)
with ``adjoint=diffrax.ForwardMode()``, as in diffrax. The saved states are the loop's write-only
buffers: every member writes once per iteration (one batched scatter), into its next save column
when it lands on a save time and into a spare column otherwise, so checkpoints never copy them.

The GPU kernel backend is `jaxlag.experimental._ensemble.pallas`.
"""

from typing import Any

import diffrax
import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ... import _errors as failures
from ..._checks import initial_state_diagnostics, validate_initial_state
from ..._custom_types import Args, RealScalarLike
from ..._errors import FailureCode
from ..._mechanics.constant_mass import ConstantMass, with_constant_mass
from ..._solver.guard import _ULPS
from ..._solver.validation import solver_controller_message
from ..._stabilization import Baumgarte, Projection
from ..._system import System
from ..._vector_field import EquationsOfMotion

__all__ = ["EnsembleSettings", "tableau_of", "integrate_ensemble", "ensemble_problem"]


def tableau_of(solver) -> diffrax.ButcherTableau:
    """The explicit Butcher tableau of a diffrax solver, or a clear error."""
    tableau = solver.tableau if isinstance(solver, diffrax.AbstractRungeKutta) else None
    if isinstance(solver, diffrax.AbstractWrappedSolver) or not isinstance(tableau, diffrax.ButcherTableau):
        raise TypeError(
            f"The ensemble integrator needs an explicit Runge–Kutta solver with a Butcher tableau "
            f"(diffrax.Tsit5(), diffrax.Dopri5(), jl.RK4(), ...); {type(solver).__name__} has none. "
            "Use simulate_batch(..., method=jl.Vmap()) for any other diffrax solver."
        )
    if tableau.a_diagonal is not None and np.any(np.asarray(tableau.a_diagonal) != 0):
        raise TypeError(
            f"{type(solver).__name__} is implicit (its tableau has a diagonal); the ensemble "
            "integrator is explicit only. Use simulate_batch(..., method=jl.Vmap())."
        )
    return tableau


class Tableau(eqx.Module):
    """A Butcher tableau as tuples of floats (hashable: it is static in the compiled program)."""

    c: tuple[float, ...] = eqx.field(static=True)
    a_lower: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    b_sol: tuple[float, ...] = eqx.field(static=True)
    b_error: tuple[float, ...] = eqx.field(static=True)
    fsal: bool = eqx.field(static=True)

    @classmethod
    def from_diffrax(cls, tableau: diffrax.ButcherTableau) -> "Tableau":
        def floats(x):
            return tuple(float(v) for v in np.asarray(x))

        return cls(
            floats(tableau.c),
            tuple(floats(a) for a in tableau.a_lower),
            floats(tableau.b_sol),
            floats(tableau.b_error),
            bool(tableau.fsal),
        )


class EnsembleSettings(eqx.Module):
    """What the loop needs to know, decided before tracing (all static except the tolerances)."""

    tableau: Tableau = eqx.field(static=True)
    adaptive: bool = eqx.field(static=True)
    error_order: float = eqx.field(static=True)
    rtol: RealScalarLike | None = None
    atol: RealScalarLike | None = None
    pcoeff: float = eqx.field(static=True, default=0.0)
    icoeff: float = eqx.field(static=True, default=1.0)
    dcoeff: float = eqx.field(static=True, default=0.0)
    safety: float = eqx.field(static=True, default=0.9)
    factormin: float = eqx.field(static=True, default=0.2)
    factormax: float = eqx.field(static=True, default=10.0)
    dtmin: RealScalarLike | None = None
    dtmax: RealScalarLike | None = None
    max_steps: int = eqx.field(static=True, default=2**16)
    loop_kind: str = eqx.field(static=True, default="checkpointed")
    throw: bool = eqx.field(static=True, default=True)  # not read by the loop: see member_failures


def _static_float(value, name):
    if isinstance(value, (int, float, np.floating, np.integer)):
        return float(value)
    try:
        return float(np.asarray(value))
    except Exception:  # noqa: BLE001
        raise TypeError(
            f"PIDController.{name} must be a concrete number for the ensemble integrator; got {value!r}."
        ) from None


def make_settings(solver, stepsize_controller, max_steps, adjoint, throw) -> EnsembleSettings:
    """Validate the diffrax objects and turn them into `EnsembleSettings`."""
    tableau = tableau_of(solver)
    if max_steps is None or int(max_steps) < 1:
        raise ValueError(
            f"max_steps must be a positive integer for the ensemble integrator; got {max_steps!r}."
        )
    if adjoint is None or isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint):
        kind = "checkpointed"
    elif isinstance(adjoint, diffrax.ForwardMode):
        kind = "lax"
    else:
        raise TypeError(
            "adjoint must be diffrax.RecursiveCheckpointAdjoint() (reverse mode, the default) or "
            f"diffrax.ForwardMode() (forward mode) for the ensemble integrator; got {adjoint!r}."
        )
    common: dict[str, Any] = dict(
        tableau=Tableau.from_diffrax(tableau), max_steps=int(max_steps), loop_kind=kind, throw=bool(throw)
    )
    if isinstance(stepsize_controller, diffrax.ConstantStepSize):
        return EnsembleSettings(adaptive=False, error_order=0.0, **common)
    if type(stepsize_controller) is not diffrax.PIDController:
        raise TypeError(
            "stepsize_controller must be diffrax.ConstantStepSize() or diffrax.PIDController(...) "
            f"for the ensemble integrator; got {type(stepsize_controller).__name__}. Use "
            "simulate_batch(..., method=jl.Vmap())."
        )
    controller = stepsize_controller
    text = solver_controller_message(solver, controller)
    if text is not None:
        raise ValueError(text)
    if controller.norm is not optx.rms_norm:
        raise ValueError(
            "The ensemble integrator uses diffrax's default RMS error norm; a custom "
            "PIDController.norm is not supported (use method=jl.Vmap())."
        )
    if not controller.force_dtmin:
        raise ValueError(
            "PIDController(force_dtmin=False) is not supported by the ensemble "
            "integrator (use method=jl.Vmap())."
        )
    error_order = controller.error_order
    if error_order is None:
        error_order = solver.error_order(diffrax.ODETerm(lambda t, y, a: y))
    return EnsembleSettings(
        adaptive=True,
        error_order=_static_float(error_order, "error_order"),
        rtol=controller.rtol,
        atol=controller.atol,
        pcoeff=_static_float(controller.pcoeff, "pcoeff"),
        icoeff=_static_float(controller.icoeff, "icoeff"),
        dcoeff=_static_float(controller.dcoeff, "dcoeff"),
        safety=_static_float(controller.safety, "safety"),
        factormin=_static_float(controller.factormin, "factormin"),
        factormax=_static_float(controller.factormax, "factormax"),
        dtmin=controller.dtmin,
        dtmax=controller.dtmax,
        **common,
    )


# --------------------------------------------------------------------------------------------
# The batched vector field and Runge–Kutta step
# --------------------------------------------------------------------------------------------


class BatchedField(eqx.Module):
    """``(t (B,), (q, q̇) (B, n)) ↦ ((q̇, q̈), ...)``: the equations of motion vmapped over members.

    ``member_args`` have a leading batch axis on every leaf, ``shared_args`` none;
    ``constant_mass`` is the per-member `ConstantMass` (or ``None``).
    """

    system: System
    baumgarte: Baumgarte | None
    projection: Projection | None
    member_args: Args
    shared_args: Args
    constant_mass: ConstantMass | None

    def _system(self, constant_mass):
        if constant_mass is None:
            return self.system
        return eqx.tree_at(lambda s: s.constant_mass, self.system, constant_mass, is_leaf=lambda x: x is None)

    def _args(self, member):
        return eqx.combine(member, self.shared_args)

    def __call__(self, t, y):
        def one(ti, qi, qdi, member, constant_mass):
            field = EquationsOfMotion(self._system(constant_mass), self.baumgarte)
            return field(ti, (qi, qdi), self._args(member))

        return jax.vmap(one)(t, y[0], y[1], self.member_args, self.constant_mass)

    def project(self, t, y):
        projection = self.projection
        if projection is None:
            return y

        def one(ti, qi, qdi, member, constant_mass):
            return projection(self._system(constant_mass), qi, qdi, ti, self._args(member))

        return jax.vmap(one)(t, y[0], y[1], self.member_args, self.constant_mass)


def _combine(y, h, coefficients, ks):
    """``y + h Σ c_j k_j`` (zero coefficients skipped; ``h`` per member, shape (B,))."""
    total = None
    for c, k in zip(coefficients, ks):
        if c == 0:
            continue
        term = jax.tree.map(lambda x: float(c) * x, k)
        total = term if total is None else jax.tree.map(jnp.add, total, term)
    if total is None:
        return y
    return jax.tree.map(lambda a, s: a + h[:, None] * s, y, total)


def rk_step(field, tableau, t, h, y, f0):
    """One explicit Runge–Kutta step of every member: ``(y₁, e, f(t + c_last h, ·))``.

    ``f0 = f(t, y)``; for first-same-as-last tableaus the returned last stage is ``f(t + h, y₁)``.
    """
    ks = [f0]
    for c, a in zip(tableau.c, tableau.a_lower):
        ks.append(field(t + float(c) * h, _combine(y, h, a, ks)))
    y1 = _combine(y, h, tableau.b_sol, ks)
    error = _combine(jax.tree.map(jnp.zeros_like, y), h, tableau.b_error, ks)
    return y1, error, ks[-1]


def select(mask, new, old):
    return jax.tree.map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old
    )


# --------------------------------------------------------------------------------------------
# Constant steps
# --------------------------------------------------------------------------------------------


def constant_grid(ts: np.ndarray, dt0: float):
    """Steps per save interval: ``m[b, k] = ceil((t_{k+1} − t_k)/dt0)`` (round-off tolerant).

    ``ts`` (B, T) concrete. Returns ``m`` (B, T−1) int and the static inner length ``max m``.
    """
    intervals = np.diff(ts, axis=1)
    ratio = intervals / dt0
    m = np.ceil(ratio - 1e-9 * np.maximum(1.0, ratio)).astype(np.int64)
    m = np.maximum(m, 1)
    return m, int(m.max()) if m.size else 0


def constant_loop(field, settings, ts, y0, steps_per_interval, inner, uniform):
    """Constant steps: scan over save intervals, inner scan over the steps of each interval."""
    tableau = settings.tableau
    fsal = tableau.fsal
    m = jnp.asarray(steps_per_interval, jnp.int32).T  # (T-1, B)
    starts = ts[:, :-1].T  # (T-1, B)
    h_all = jnp.diff(ts, axis=1).T / m.astype(ts.dtype)

    @jax.checkpoint
    def step(carry, j, t_start, h, m_k):
        y, f = carry
        t = t_start + j.astype(h.dtype) * h
        f0 = f if fsal else field(t, y)
        y1, _, f_last = rk_step(field, tableau, t, h, y, f0)
        t1 = jnp.where(j + 1 == m_k, t_start + m_k.astype(h.dtype) * h, t + h)
        y1 = field.project(t1, y1)
        # First-same-as-last: the last stage is f at the unprojected end state, reused as the next
        # first stage exactly as diffrax's ProjectedSolver does (it differs from f at the projected
        # state by one step's drift).
        f_next = f_last if fsal else f
        if not uniform:
            active = j < m_k
            y1 = select(active, y1, y)
            f_next = select(active, f_next, f) if fsal else f_next
        return (y1, f_next), None

    def interval(carry, xs):
        t_start, h, m_k = xs
        carry, _ = jax.lax.scan(
            lambda c, j: step(c, j, t_start, h, m_k), carry, jnp.arange(inner, dtype=jnp.int32)
        )
        return carry, carry[0]

    f0 = field(ts[:, 0], y0) if fsal else None
    _, saved = jax.lax.scan(interval, (y0, f0), (starts, h_all, m))
    counts = jnp.sum(m, axis=0, dtype=jnp.int32)
    return (
        saved,
        {"num_steps": counts, "num_accepted_steps": counts, "num_rejected_steps": jnp.zeros_like(counts)},
        jnp.ones(counts.shape, bool),
    )


# --------------------------------------------------------------------------------------------
# Adaptive steps
# --------------------------------------------------------------------------------------------


def _rms(tree, size):
    return jnp.sqrt(sum(jnp.sum(x * x, axis=-1) for x in jax.tree.leaves(tree)) / size)


def _initial_step(field, settings, t0, y0, f0):
    """Hairer's starting step, as diffrax's ``PIDController`` chooses it, per member."""
    size = 2 * y0[0].shape[1]
    t0, y0, f0 = jax.lax.stop_gradient((t0, y0, f0))
    scale = jax.tree.map(lambda y: settings.atol + jnp.abs(y) * settings.rtol, y0)
    d0 = _rms(jax.tree.map(jnp.divide, y0, scale), size)
    d1 = _rms(jax.tree.map(jnp.divide, f0, scale), size)
    small = (d0 < 1e-5) | (d1 < 1e-5)
    h0 = jnp.where(small, 1e-6, 0.01 * d0 / jnp.where(small, 1.0, d1))
    y1 = jax.tree.map(lambda y, f: y + h0[:, None] * f, y0, f0)
    f1 = field(t0 + h0, y1)
    d2 = _rms(jax.tree.map(lambda a, b, s: (a - b) / s, f1, f0, scale), size) / h0
    max_d = jnp.maximum(d1, d2)
    h1 = jnp.where(
        max_d <= 1e-15,
        jnp.maximum(1e-6, h0 * 1e-3),
        (0.01 / jnp.where(max_d <= 1e-15, 1.0, max_d)) ** (1 / settings.error_order),
    )
    return jax.lax.stop_gradient(jnp.minimum(100 * h0, h1))


class AdaptiveState(eqx.Module):
    """The adaptive loop's carry, every entry per member (leading axis ``B``): time ``t``, the
    next step ``dt`` to try, the state ``y = (q, q̇)``, the last stage ``f = f(t, y)`` for
    first-same-as-last tableaus (else ``None``), the next save column ``k``, the save buffers
    (``(B, T + 1, n)`` each, the last column a spare), the PID controller's ``1/ε`` of the last
    and the one before (``inv``, ``inv_prev``), whether ``dt`` is at ``dtmin``, the step counts,
    whether the member failed (and with a non-finite trial state) and the last step tried."""

    t: Float[Array, " batch"]
    dt: Float[Array, " batch"]
    y: tuple[Float[Array, "batch n"], Float[Array, "batch n"]]
    f: tuple[Float[Array, "batch n"], Float[Array, "batch n"]] | None
    k: Int[Array, " batch"]
    saves: tuple[Float[Array, "batch saves n"], Float[Array, "batch saves n"]]
    inv: Float[Array, " batch"]
    inv_prev: Float[Array, " batch"]
    at_dtmin: Bool[Array, " batch"]
    accepted: Int[Array, " batch"]
    rejected: Int[Array, " batch"]
    failed: Bool[Array, " batch"]
    nonfinite: Bool[Array, " batch"]
    last_dt: Float[Array, " batch"]


def _adaptive_loop(field, settings, ts, y0, dt0):
    tableau = settings.tableau
    fsal = tableau.fsal
    batch, num_saves = ts.shape
    n = y0[0].shape[1]
    dtype = ts.dtype
    members = jnp.arange(batch)
    t0 = ts[:, 0]
    f0 = field(t0, y0)
    if dt0 is None:
        dt = _initial_step(field, settings, t0, y0, f0)
    else:
        dt = jnp.broadcast_to(jnp.asarray(dt0, dtype), (batch,))
    if settings.dtmax is not None:
        dt = jnp.minimum(dt, settings.dtmax)
    if settings.dtmin is not None:
        dt = jnp.maximum(dt, settings.dtmin)
    # One spare column: members that do not save this iteration write there (see below).
    saves = (jnp.zeros((batch, num_saves + 1, n), dtype), jnp.zeros((batch, num_saves + 1, n), dtype))
    p = settings.error_order
    beta1 = (settings.pcoeff + settings.icoeff + settings.dcoeff) / p
    beta2 = -(settings.pcoeff + 2 * settings.dcoeff) / p
    beta3 = settings.dcoeff / p
    ones = jnp.ones((batch,), dtype)
    zero = jnp.zeros((batch,), jnp.int32)
    init = AdaptiveState(
        t=t0,
        dt=dt,
        y=y0,
        f=f0 if fsal else None,
        k=jnp.ones((batch,), jnp.int32),
        saves=saves,
        inv=ones,
        inv_prev=ones,
        at_dtmin=jnp.zeros((batch,), bool),
        accepted=zero,
        rejected=zero,
        failed=jnp.zeros((batch,), bool),
        nonfinite=jnp.zeros((batch,), bool),
        last_dt=dt,
    )
    # A rejected step of round-off size ends the member (as jaxlag's FiniteStepGuard ends a
    # diffrax solve): non-finite if its trial state was, else a collapsed step size.
    scale = jnp.max(jnp.abs(ts), axis=1)
    scale = jnp.maximum(scale, ts[:, -1] - ts[:, 0])
    tiny_step = _ULPS * float(jnp.finfo(dtype).eps) * scale

    def cond(c: AdaptiveState):
        return jnp.any((c.k < num_saves) & ~c.failed)

    def body(c: AdaptiveState) -> AdaptiveState:
        running = (c.k < num_saves) & ~c.failed
        target = ts[members, jnp.minimum(c.k, num_saves - 1)]
        t, y = c.t, c.y
        remaining = target - t
        clipped = c.dt >= remaining * (1 - 1e-12)
        h = jnp.where(clipped, remaining, c.dt)
        h = jnp.where(running, h, 1e-3 * jnp.abs(c.dt) + 1e-300)  # finished: any harmless step
        t1 = jnp.where(clipped, target, t + h)
        f_start = c.f if fsal else field(t, y)
        y1, error, f_last = rk_step(field, tableau, t, h, y, f_start)
        # Step-size control is not differentiated (as in diffrax): no zero-times-infinite
        # cotangents from the norm of a vanishing error.
        scaled = jax.tree.map(
            lambda e, a, b: e / (settings.atol + jnp.maximum(jnp.abs(a), jnp.abs(b)) * settings.rtol),
            *jax.lax.stop_gradient((error, y, y1)),
        )
        err = _rms(scaled, 2 * n)
        finite = jnp.all(jnp.isfinite(y1[0]), axis=1) & jnp.all(jnp.isfinite(y1[1]), axis=1)
        err = jnp.where(finite & jnp.isfinite(err), err, jnp.inf)
        keep = err < 1
        if settings.dtmin is not None:
            keep = keep | c.at_dtmin
        inv = jax.lax.stop_gradient(1 / err)
        factor = settings.safety * inv**beta1
        if beta2 != 0:
            factor = factor * c.inv**beta2
        if beta3 != 0:
            factor = factor * c.inv_prev**beta3
        factor = jnp.clip(
            factor,
            jnp.where(keep, 1.0, settings.factormin),
            jnp.where(keep, settings.factormax, settings.safety),
        )
        factor = jax.lax.stop_gradient(factor)
        dt_next = h * factor
        dt_next = jnp.where(keep & clipped, jnp.maximum(dt_next, c.dt), dt_next)
        if settings.dtmax is not None:
            dt_next = jnp.minimum(dt_next, settings.dtmax)
        at_dtmin = c.at_dtmin
        if settings.dtmin is not None:
            at_dtmin = dt_next <= settings.dtmin
            dt_next = jnp.maximum(dt_next, settings.dtmin)
        inv = jnp.where((inv == 0) | jnp.isinf(inv), 1.0, inv)
        accept = keep & running
        fail = running & ~keep & (h <= tiny_step)
        y1 = field.project(t1, y1)
        save = accept & clipped
        # Every member writes every iteration (one batched scatter), those not saving into the
        # spare last column, which is never read. (An out-of-range index with mode="drop" would
        # do the same forward, but the checkpointed loop's reverse pass gathers the cotangent at
        # that index, and an out-of-range gather fills with NaN.)
        index = jnp.where(save, c.k, num_saves)
        saves = (c.saves[0].at[members, index].set(y1[0]), c.saves[1].at[members, index].set(y1[1]))
        return AdaptiveState(
            t=jnp.where(accept, t1, t),
            dt=jnp.where(running, dt_next, c.dt),
            y=select(accept, y1, y),
            f=select(accept, f_last, c.f) if fsal else None,
            k=c.k + save.astype(jnp.int32),
            saves=saves,
            inv=jnp.where(accept, inv, c.inv),
            inv_prev=jnp.where(accept, c.inv, c.inv_prev),
            at_dtmin=jnp.where(running, at_dtmin, c.at_dtmin),
            accepted=c.accepted + accept.astype(jnp.int32),
            rejected=c.rejected + (running & ~keep).astype(jnp.int32),
            failed=c.failed | fail,
            nonfinite=c.nonfinite | (fail & ~finite),
            last_dt=jnp.where(running, jax.lax.stop_gradient(h), c.last_dt),
        )

    if settings.loop_kind == "checkpointed":
        # The saves are write-only buffers: the checkpoints hold the small loop state only.
        final = eqxi.while_loop(
            cond, body, init, max_steps=settings.max_steps, buffers=lambda c: c.saves, kind="checkpointed"
        )
    else:
        final = eqxi.while_loop(cond, body, init, max_steps=settings.max_steps, kind="lax")
    saved = tuple(jnp.moveaxis(s[:, 1:num_saves], 1, 0) for s in final.saves)
    stats = {
        "num_steps": final.accepted + final.rejected,
        "num_accepted_steps": final.accepted,
        "num_rejected_steps": final.rejected,
    }
    code = jnp.where(
        final.failed,
        jnp.where(final.nonfinite, FailureCode.NONFINITE, FailureCode.STEP_SIZE_COLLAPSED),
        jnp.where(final.k >= num_saves, FailureCode.COMPLETED, FailureCode.MAX_STEPS),
    )
    record = LoopRecord(code.astype(jnp.int32), final.k - 1, final.t, final.last_dt, *final.y)
    return saved, stats, jax.lax.stop_gradient(record)


# --------------------------------------------------------------------------------------------
# The whole problem
# --------------------------------------------------------------------------------------------


def ensemble_problem(system, q0, qd0, ts, member_args, shared_args, baumgarte, projection, check, tolerance):
    """Checked initial states and the `BatchedField` of a batch (inside ``jit``):
    ``(field, (q0, q̇0), diagnostics)``. ``check``: ``True`` compiles the initial-state check in
    (static message), ``"host"`` returns every member's diagnostics for the host to raise with
    the numbers and the member (`raise_for_initial_states`; else
    ``diagnostics`` is ``None``), ``False`` skips it."""

    def prepare(q, qd, t, member):
        args = eqx.combine(member, shared_args)
        system.check(q, qd, t, args)
        diagnostics = None
        if check == "host":
            diagnostics = initial_state_diagnostics(system, q, qd, t, args, tolerance)
        elif check:
            q, qd = validate_initial_state(system, q, qd, t, args, tolerance)
        fast = with_constant_mass(system, q, qd, t, args)
        return q, qd, fast.constant_mass, diagnostics

    q0, qd0, constant_mass, diagnostics = eqx.filter_vmap(prepare)(q0, qd0, ts[:, 0], member_args)
    field = BatchedField(system, baumgarte, projection, member_args, shared_args, constant_mass)
    return field, (q0, qd0), diagnostics


def integrate_ensemble(field, settings, ts, y0, dt0, grid=None):
    """Run the loop; returns ``(saved (q, q̇) each (T−1, B, n), stats, record)``: ``record``
    the adaptive loop's `LoopRecord`, ``None`` for constant steps (every member runs to
    its end; `member_failures` finds the non-finite ones).

    ``ts`` (B, T), the first column being the start times; ``grid = (m, inner, uniform)`` for
    constant steps: ``m`` (B, T−1) steps per save interval (see `constant_grid`), ``inner``
    its maximum (static) and ``uniform`` whether every entry equals it (static).
    """
    if settings.adaptive:
        return _adaptive_loop(field, settings, ts, y0, dt0)
    if grid is None:
        raise ValueError("integrate_ensemble needs grid=(m, inner, uniform) for constant steps.")
    steps_per_interval, inner, uniform = grid[:3]
    saved, stats, _ = constant_loop(field, settings, ts, y0, steps_per_interval, inner, uniform)
    return saved, stats, None


class LoopRecord(eqx.Module):
    """How the adaptive loop ended for each member (leading axis B): ``code`` (the results
    enumeration of `jaxlag._errors`), ``reached`` (save columns written, start excluded),
    ``t`` (time reached), ``dt`` (last step tried) and ``q``, ``qd`` (last accepted state)."""

    code: Int[Array, " batch"]
    reached: Int[Array, " batch"]
    t: Float[Array, " batch"]
    dt: Float[Array, " batch"]
    q: Float[Array, "batch n"]
    qd: Float[Array, "batch n"]


def _result_of(code):
    """The diffrax result of one member (the guard of ``jl.simulate`` reports a non-finite
    or collapsed step as ``dt_min_reached``)."""
    results = diffrax.RESULTS
    stopped = results.where(code == FailureCode.MAX_STEPS, results.max_steps_reached, results.dt_min_reached)
    return results.where(code == FailureCode.COMPLETED, results.successful, stopped)


def member_failures(ts, y0, saved, stats, record, steps_per_interval, max_steps):
    """Each member's `Failure` record, its diffrax result and its saves
    with the unreached ones set to ``inf`` (diffrax's and ``jl.Vmap()``'s convention).

    ``saved`` (q, q̇) each (T−1, B, n); ``record`` the adaptive loop's `LoopRecord`, or
    ``None`` for constant steps (every save is reached), with ``steps_per_interval`` (B, T−1).
    Either way a member whose saved state is non-finite failed there (code 1, non-finite): a
    constant step cannot be shrunk, and the Pallas kernel and the constant-step loop do not stop
    a member whose state became NaN. It is reported at its last finite save (``t``, ``q``, ``q̇``
    there; ``dt`` the step of the interval that blew up). Works for every backend: it reads the
    saves only."""
    q_saved, qd_saved = saved
    intervals, batch = q_saved.shape[:2]
    members = jnp.arange(batch)
    if record is None:
        h = jnp.diff(ts, axis=1) / jnp.asarray(steps_per_interval, ts.dtype)  # (B, T-1)
        record = LoopRecord(
            jnp.full((batch,), FailureCode.COMPLETED, jnp.int32),
            jnp.full((batch,), intervals, jnp.int32),
            ts[:, -1],
            h[:, -1],
            q_saved[-1],
            qd_saved[-1],
        )
    else:
        h = None
    saved = jax.lax.stop_gradient(saved)
    column = jnp.arange(intervals, dtype=record.reached.dtype)[:, None]  # (T-1, 1)
    finite = jnp.all(jnp.isfinite(saved[0]), axis=-1) & jnp.all(jnp.isfinite(saved[1]), axis=-1)
    bad = ~finite & (column < record.reached[None, :])  # (T-1, B)
    first = jnp.argmax(bad, axis=0).astype(record.reached.dtype)
    late = (record.code == FailureCode.COMPLETED) & jnp.any(bad, axis=0)
    before = jnp.maximum(first - 1, 0)

    def last_good(saves, start):
        return jnp.where((first > 0)[:, None], saves[before, members], start)

    y0 = jax.lax.stop_gradient(y0)
    dt_late = record.dt if h is None else h[members, first]
    record = LoopRecord(
        jnp.where(late, FailureCode.NONFINITE, record.code),
        jnp.where(late, first, record.reached),
        jnp.where(late, ts[members, first], record.t),
        jnp.where(late, dt_late, record.dt),
        jnp.where(late[:, None], last_good(saved[0], y0[0]), record.q),
        jnp.where(late[:, None], last_good(saved[1], y0[1]), record.qd),
    )
    unreached = (column >= record.reached[None, :])[:, :, None]
    q_out, qd_out = (jnp.where(unreached, jnp.inf, x) for x in (q_saved, qd_saved))
    result = jax.vmap(_result_of)(record.code)
    failure = failures.Failure(
        code=record.code,
        t=record.t,
        dt=record.dt,
        q=record.q,
        qd=record.qd,
        t0=ts[:, 0],
        t1=ts[:, -1],
        num_steps=jnp.asarray(stats["num_steps"], jnp.int32),
        result=jnp.asarray(result._value, jnp.int32),
        max_steps=max_steps,
    )
    return (q_out, qd_out), failure, result


def as_member_times(ts, batch, dtype):
    """``ts`` as (B, T): shared (T,) rows broadcast, or per member (B, T)."""
    ts = jnp.asarray(ts, dtype=dtype)
    if ts.ndim == 1:
        ts = jnp.broadcast_to(ts, (batch, ts.shape[0]))
    if ts.ndim != 2 or ts.shape[0] != batch or ts.shape[1] < 2:
        raise ValueError(
            f"ts must have shape (T,) or (B, T) with T ≥ 2 for the ensemble integrator (B = {batch}); "
            f"got {ts.shape}."
        )
    return ts
