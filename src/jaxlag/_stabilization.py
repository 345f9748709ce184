r"""Drift control for the index-1 (acceleration-level) formulation.

Integrating ``G q̈ = c`` keeps ``f̈ = 0`` but lets ``f`` and ``ḟ`` drift with the truncation
error. Two remedies, usable together:

* `Baumgarte` adds feedback to the acceleration constraint,
  ``f̈ + 2α ḟ + β² f = 0`` (holonomic) and ``ġ + 2α g = 0`` (velocity constraints). ``α = β``
  gives critical damping of the drift; rates of order the inverse time step the solver takes
  (or of the fastest physical frequency) work well. Too large makes the system stiff.
* `Projection` moves each accepted step back onto the constraint manifold:
  positions by Newton iterations of the mass-weighted minimal correction

      q ← q − M⁻¹Jᵀ (J M⁻¹ Jᵀ)⁻¹ f(q, t),

  then velocities onto ``J q̇ + ∂f/∂t = 0`` and ``A q̇ + b = 0`` by the exact linear projection
  ``q̇ ← q̇ − M⁻¹Gᵀ (G M⁻¹ Gᵀ)⁻¹ r`` with ``r = [ḟ; g]``. It wraps the diffrax solver
  (`ProjectedSolver`), so error control sees the unprojected step and the projection
  is applied before the next step starts.
"""

from collections.abc import Sequence
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool

from . import _compile as compilation
from ._conventions import as_array_leaves, as_jax_array, as_jit_inputs
from ._custom_types import Args, Coordinates, RealScalarLike, Vector, Velocities
from ._errors import compiled_check
from ._mechanics import constraints as _constraints
from ._mechanics.kkt import deactivate
from ._mechanics.lagrangian import as_time, mass_matrix, mass_solver
from ._mechanics.linalg import solve_psd_least_squares, solve_spd, spd_solver
from ._misc import is_concrete
from ._solver.forwarding import ForwardingSolver
from ._system import System
from ._tolerances import CONSTRAINT_RCOND, rcond


class Baumgarte(eqx.Module):
    """Baumgarte stabilization: ``f̈ + 2α ḟ + β² f = 0`` and ``ġ + 2α g = 0``.

    ``alpha`` and ``beta`` are rates in 1/time; ``Baumgarte(alpha=10.0, beta=10.0)`` damps drift
    critically on a 0.1 time-unit scale.
    """

    alpha: RealScalarLike = 10.0
    beta: RealScalarLike = 10.0


def _schur_correction(system, solve_mass, rows, residual, active=None):
    """``M⁻¹Gᵀ (G M⁻¹ Gᵀ)⁻¹ r``: the M-weighted minimal change that removes the linear residual.

    ``solve_mass`` applies ``M⁻¹`` (factored once per projection). Rows whose ``active`` entry
    is zero are left out (see `jaxlag._mechanics.kkt.deactivate`).
    """
    rows, residual, pad = deactivate(rows, residual, active)
    minv_gt = solve_mass(rows.T)
    schur = rows @ minv_gt
    if pad is not None:
        schur = schur + pad
    if system.least_squares:
        return minv_gt @ solve_psd_least_squares(schur, residual)
    return minv_gt @ solve_spd(schur, residual)


def _held_mass_solver(system, q, qd, t, args, free):
    """``b ↦ M̃⁻¹ b`` with ``M̃ = S M S + (I − S)``, ``S = diag(free)``: the metric restricted to
    the free coordinates (block ``M_ff``) and the identity on the held ones. With the held
    columns of the constraint rows zeroed, the correction ``M̃⁻¹Gᵀ(G M̃⁻¹ Gᵀ)⁻¹ r`` is the
    ``M_ff``-weighted minimal change of the free coordinates and leaves the held ones alone."""
    if free is None:
        return mass_solver(system, q, qd, t, args)
    metric = mass_matrix(system, q, qd, t, args) * jnp.outer(free, free) + jnp.diag(1.0 - free)
    return spd_solver(metric)


def _hold(rows, free):
    return rows if free is None else rows * free[None, :]


def project_state(
    system,
    q,
    qd,
    t,
    args,
    newton_steps: int = 2,
    active=None,
    refresh_mass: bool = False,
    free_q=None,
    free_qd=None,
):
    """Project ``(q, q̇)`` onto ``f = 0``, ``ḟ = 0``, ``g = 0`` in the metric of ``M(q, q̇)``.

    The metric is ``M`` at the incoming state, factored once and held fixed through the Newton
    iterations, so the position correction is the mass-weighted minimal one to first order in
    its size. With ``refresh_mass`` the velocity projection uses ``M`` at the corrected position
    (exactly minimal there); per-step projection skips that, as the correction is at the level
    of the local error. ``active`` (m_h,) optionally restricts the holonomic constraints.
    ``free_q``, ``free_qd`` (n,) optionally mark with 1 the coordinates (velocities) that may
    move; the others are held at their incoming values.
    """
    t = as_time(t, q)
    solve_mass = _held_mass_solver(system, q, qd, t, args, free_q)
    if system.holonomic is not None:

        def newton(_, x):
            f = _constraints.holonomic_residual(system, x, t, args)
            jac = _hold(_constraints.holonomic_jacobian(system, x, t, args, f.shape[0]), free_q)
            return x - _schur_correction(system, solve_mass, jac, f, active)

        # One traced Newton step in a loop, not newton_steps copies: a smaller program.
        q = jax.lax.fori_loop(0, newton_steps, newton, q)
    if (refresh_mass and system.holonomic is not None) or free_q is not None or free_qd is not None:
        solve_mass = _held_mass_solver(system, q, qd, t, args, free_qd)
    rows, residual = [], []
    if system.holonomic is not None:

        def f_of(x, s):
            return _constraints.holonomic_residual(system, x, s, args)

        # ḟ = J q̇ + ∂f/∂t in one forward pass; J itself for the projection rows.
        _, f_dot = jax.jvp(f_of, (q, t), (qd, jnp.ones_like(t)))
        rows.append(_constraints.holonomic_jacobian(system, q, t, args, f_dot.shape[0]))
        residual.append(f_dot)
    if system.velocity_constraints is not None:
        g, a, _ = _constraints.velocity_terms(system, q, qd, t, args)
        rows.append(a)
        residual.append(g)
    if rows:
        rows, residual = _hold(jnp.concatenate(rows), free_qd), jnp.concatenate(residual)
        if active is not None:
            active = jnp.concatenate(
                [jnp.asarray(active, q.dtype), jnp.ones((rows.shape[0] - active.shape[0],), q.dtype)]
            )
        qd = qd - _schur_correction(system, solve_mass, rows, residual, active)
    return q, qd


class Projection(eqx.Module):
    """Project onto the constraint manifold after every accepted step and at every saved time.

    ``newton_steps`` position iterations per step. Newton squares the residual, so two take a
    drift of 1e-4 per step (large constant steps) to round-off; at adaptive tolerances one would
    do. The mass matrix is factored once per projection, so extra iterations are cheap.
    """

    newton_steps: int = eqx.field(static=True, default=2)

    def __call__(
        self,
        system: System,
        q: Vector,
        qd: Vector,
        t: RealScalarLike,
        args: Args,
        active: Bool[Array, " m_h"] | None = None,
    ) -> tuple[Vector, Vector]:
        t, args = as_jit_inputs(t, args, q.dtype)
        return _projected(system, q, qd, t, args, self.newton_steps, active)


# Jitted: the step's projection, the projection of the saved states (its vmap) and the pushed
# projection of the forward sensitivities share one trace of it.
@compilation.filter_jit
def _projected(system, q, qd, t, args, newton_steps, active):
    """`Projection.__call__`."""
    return project_state(system, q, qd, t, args, newton_steps, active)


class ProjectedSolver(ForwardingSolver, diffrax.AbstractWrappedSolver):
    """A diffrax solver wrapper that projects each step's end state onto the constraint manifold.

    The wrapped solver's error estimate (of the unprojected step) drives step-size control; the
    first-same-as-last stage that some solvers carry to the next step is the unprojected one,
    which differs from the projected state by the drift of a single step (at the level of the
    local error) and so does not change the order of the method. diffrax's ForwardMode reads
    ``scan_kind`` on Runge–Kutta solvers (``isinstance`` is forwarded to the inner solver): the
    forwarded field, see `wrap_for_projection`.
    """

    solver: diffrax.AbstractSolver  # pyright: ignore[reportIncompatibleVariableOverride]
    system: Any
    projection: Projection
    active: Any = None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, made_jump
        )
        q1, qd1 = self.projection(self.system, y1[0], y1[1], t1, args, self.active)
        return (q1, qd1), y_error, dense_info, solver_state, result


def _free_mask(indices, n, dtype, name):
    if isinstance(indices, int):
        indices = (indices,)
    indices = tuple(indices)
    bad = [i for i in indices if not hasattr(i, "__index__") or not 0 <= int(i) < n]
    if bad:
        raise ValueError(f"{name} must hold coordinate indices in [0, {n}); got {bad}.")
    indices = tuple(int(i) for i in indices)
    if not indices:
        return None
    mask = np.ones((n,), np.dtype(dtype))  # on the host: no eager device program per shape
    mask[list(indices)] = 0.0
    return mask


def consistent_initial_state(
    system: System,
    q0: Coordinates,
    qd0: Velocities,
    t0: RealScalarLike = 0.0,
    args: Args = None,
    *,
    fixed_q: int | Sequence[int] = (),
    fixed_qd: int | Sequence[int] = (),
    newton_steps: int = 20,
    tolerance: float | None = None,
) -> tuple[Vector, Vector]:
    """Project an approximate initial state onto the constraint manifold.

    Positions move by the mass-weighted minimal correction (Newton, ``newton_steps`` fixed
    iterations, so the result is differentiable with ``jax.grad``), then velocities by the
    exact linear projection. Raises (also under ``jit``) if the position residual is still
    above ``tolerance`` afterwards (default 1e-10 in float64, ``√ε`` = 3.5e-4 in float32), e.g.
    for constraints that cannot all hold at once.

    ``fixed_q`` and ``fixed_qd`` (indices into ``q``) hold chosen coordinates and velocities at
    their given values while the others are solved for: e.g. the crank angle and crank rate of a
    four-bar linkage, the other link angles following from the loop closure. The correction is
    then minimal in the metric ``M_ff`` of the free coordinates. Holding too many (fewer free
    coordinates than independent constraints, or a configuration the loop cannot reach) leaves
    a residual and raises.

    Returns ``(q0, qd0)`` with ``f(q0) = 0``, ``J q̇0 + ∂f/∂t = 0`` and ``A q̇0 + b = 0``.
    """
    q0 = as_jax_array(q0, jnp.result_type(float))
    qd0 = as_jax_array(qd0, q0.dtype)
    if tolerance is None:
        tolerance = default_projection_tolerance(q0.dtype)
    system.check(q0, qd0, t0, args)
    n = q0.shape[0]
    free_q = _free_mask(fixed_q, n, q0.dtype, "fixed_q")
    free_qd = _free_mask(fixed_qd, n, q0.dtype, "fixed_qd")
    # A concrete time stays on the host (NumPy) until the compiled call: no eager conversion.
    t0 = jnp.asarray(t0, dtype=q0.dtype) if isinstance(t0, jax.Array) else np.asarray(t0, dtype=q0.dtype)
    args = as_array_leaves(args, q0.dtype)
    if is_concrete((q0, qd0, t0, args)):
        # Eager: the projection without its compiled checks, then the check on the host, whose
        # message names the constraint rows and the held coordinates.
        q, qd, position, velocity, rows = jax.device_get(
            _projection_and_rows(system, q0, qd0, t0, args, newton_steps, free_q, free_qd)
        )
        if is_concrete((q, qd, position, velocity, rows)):
            text = _projection_message(
                system, q, position, velocity, rows, tolerance, fixed_q, fixed_qd, free_q, free_qd
            )
            if text is not None:
                raise ValueError(text)
            return jnp.asarray(q), jnp.asarray(qd)
    return _consistent_state(system, q0, qd0, t0, args, newton_steps, tolerance, free_q, free_qd)


_POSITION_MESSAGE = (
    "consistent_initial_state: Newton projection did not reach the constraint manifold within "
    "tolerance {tolerance:g} (constraints inconsistent, the starting guess too far from any "
    "solution, or too many coordinates held fixed; state dtype {dtype})."
)


def projection_with_residuals(system, q0, qd0, t0, args, newton_steps=20, free_q=None, free_qd=None):
    """``(q, qd, position_residual, velocity_residual)``: the projection of
    `consistent_initial_state` without its checks, and what they test: ``max |f(q)|`` and
    (with ``free_qd``) ``max |(ḟ, g)|`` (zeros where there is nothing to test). For callers that
    check on the host after their program has run (``jl.fit``): no host callback is compiled."""
    q, qd = project_state(
        system, q0, qd0, t0, args, newton_steps, refresh_mass=True, free_q=free_q, free_qd=free_qd
    )
    zero = jnp.zeros((), q.dtype)
    position = zero
    if system.holonomic is not None:
        f = _constraints.holonomic_residual(system, q, t0, args)
        position = jnp.max(jnp.abs(f), initial=0.0)
    velocity = zero
    if free_qd is not None:
        _, f_dot, g = _constraints.constraint_residuals(system, q, qd, t0, args)
        velocity = jnp.max(jnp.abs(jnp.concatenate([f_dot, g])), initial=0.0)
    return q, qd, position, velocity


def default_projection_tolerance(dtype) -> float:
    """The default ``tolerance`` of `consistent_initial_state`: 1e-10 in float64, ``√ε``
    of lower precisions (3.5e-4 in float32)."""
    eps = float(jnp.finfo(dtype).eps)
    return 1e-10 if eps <= float(jnp.finfo(jnp.float64).eps) else eps**0.5


def position_failure_message(tolerance, dtype) -> str:
    """The error of `consistent_initial_state` when the positions stay off the manifold."""
    return _POSITION_MESSAGE.format(tolerance=tolerance, dtype=np.dtype(dtype))


def _rows_at(system, q, qd, t, args):
    """``(J, [J; A])``: the holonomic Jacobian (m_h, n) and all velocity-level rows (m, n)."""
    rows, _ = _constraints.constraint_rows(system, q, qd, t, args)
    m_h = system.num_holonomic(q, t, args)
    return rows[:m_h], rows


# One compiled program per system and shapes: eager, the Newton loop would dispatch (and compile)
# every small operation separately.
@compilation.filter_jit
def _projection_and_rows(system, q0, qd0, t0, args, newton_steps, free_q, free_qd):
    q, qd, position, velocity = projection_with_residuals(
        system, q0, qd0, t0, args, newton_steps, free_q, free_qd
    )
    return q, qd, position, velocity, _finite_rows(system, q, qd, q0, qd0, t0, args)


def _finite_rows(system, q, qd, q0, qd0, t0, args):
    """The rows of `_rows_at` at the projected state, or at the given one where the
    projection went non-finite (a singular correction when nothing can move)."""
    final = _rows_at(system, q, qd, t0, args)
    start = _rows_at(system, q0, qd0, t0, args)
    ok = jnp.all(jnp.isfinite(final[1]))
    return jax.tree.map(lambda a, b: jnp.where(ok, a, b), final, start)


def _free_rank_deficient(rows, free):
    """Whether ``rows`` restricted to the free columns have lower rank than the rows count
    (traceable): some row is left without a free coordinate of its own."""
    if rows.shape[0] == 0:
        return jnp.asarray(False)
    held = rows if free is None else rows * free[None, :]
    sv = jnp.linalg.svd(held, compute_uv=False)
    threshold = rcond(CONSTRAINT_RCOND, rows.dtype) * jnp.maximum(jnp.max(jnp.abs(rows)), 1e-300)
    return jnp.sum(sv > threshold) < rows.shape[0]


_TOO_MANY_HELD_Q = (
    "consistent_initial_state: more coordinates are held in fixed_q than the constraints allow: "
    "the position constraint Jacobian restricted to the free coordinates is rank deficient, so "
    "some constraint row is left without a free coordinate. Hold fewer coordinates. (Raised "
    "inside a compiled program: call it outside jit/vmap/grad to see which rows.)"
)
_TOO_MANY_HELD_QD = (
    "consistent_initial_state: more velocities are held in fixed_qd than the velocity "
    "constraints allow: the constraint rows restricted to the free velocities are rank "
    "deficient, so some row is left without a free velocity. Hold fewer. (Raised inside a "
    "compiled program: call it outside jit/vmap/grad to see which rows.)"
)


@compilation.filter_jit
def _consistent_state(system, q0, qd0, t0, args, newton_steps, tolerance, free_q, free_qd):
    q, qd, position, velocity = projection_with_residuals(
        system, q0, qd0, t0, args, newton_steps, free_q, free_qd
    )
    jac, rows = _finite_rows(system, q, qd, q0, qd0, t0, args)
    if system.holonomic is not None:
        failed = ~(position <= tolerance)
        cause = jnp.where(_free_rank_deficient(jac, free_q), 0, 1) if free_q is not None else 1
        q = compiled_check(
            q, failed, cause, (_TOO_MANY_HELD_Q, position_failure_message(tolerance, q0.dtype))
        )
    if free_qd is not None:
        cause = jnp.where(_free_rank_deficient(rows, free_qd), 0, 1)
        qd = compiled_check(
            qd,
            ~(velocity <= tolerance),
            cause,
            (
                _TOO_MANY_HELD_QD,
                "consistent_initial_state: the velocity constraints cannot hold with the velocities "
                "in fixed_qd held at these values (incompatible values).",
            ),
        )
    return q, qd


def _names(indices) -> str:
    return ", ".join(f"q[{int(i)}]" for i in indices)


def _rows_without_free(rows, free, m_h, level: str, fixed, fixed_name: str) -> str | None:
    """If ``rows`` restricted to the free columns are rank deficient: the message naming the
    rows left without a free coordinate, and which held coordinates would give them one."""
    rows = np.asarray(rows)
    free_mask = np.ones(rows.shape[1], bool) if free is None else np.asarray(free) > 0
    if rows.shape[0] == 0:
        return None
    threshold = rcond(CONSTRAINT_RCOND, rows.dtype) * max(float(np.max(np.abs(rows))), 1e-300)

    def rank(matrix):
        if matrix.size == 0:
            return 0
        return int(np.sum(np.linalg.svd(matrix, compute_uv=False) > threshold))

    restricted = rows[:, free_mask]
    r = rank(restricted)
    m = rows.shape[0]
    if r == m:
        return None
    name = lambda i: f"holonomic[{i}]" if i < m_h else f"velocity[{i - m_h}]"  # noqa: E731
    kept, left = [], []
    for i in range(m):
        if rank(np.array(kept + [restricted[i]])) == len(kept) + 1:
            kept.append(restricted[i])
        else:
            alone = not np.any(np.abs(restricted[i]) > threshold)
            involved = np.flatnonzero(np.abs(rows[i]) > threshold)
            left.append(
                f"{name(i)} (it involves only held {'coordinates' if level == 'q' else 'velocities'} "
                f"{_names(involved) if level == 'q' else _names(involved).replace('q[', 'q̇[')})"
                if alone
                else f"{name(i)} (in the free {'coordinates' if level == 'q' else 'velocities'} it is "
                "a combination of the rows before it)"
            )
    held = np.flatnonzero(~free_mask)
    helps = [int(k) for k in held if rank(rows[:, free_mask | (np.arange(rows.shape[1]) == k)]) > r]
    symbol = "q" if level == "q" else "q̇"
    free_names = ", ".join(f"{symbol}[{int(i)}]" for i in np.flatnonzero(free_mask)) or "none"
    text = (
        f"consistent_initial_state: {fixed_name}={tuple(int(i) for i in fixed)} holds more "
        f"{'coordinates' if level == 'q' else 'velocities'} than the constraints allow: "
        f"{int(np.sum(free_mask))} free ({free_names}) for {m} "
        f"{'position constraints' if level == 'q' else 'velocity-level constraint rows'}, and the "
        f"constraint rows restricted to the free ones have rank {r} < {m}. Left without a free "
        f"{'coordinate' if level == 'q' else 'velocity'}: {'; '.join(left)}."
    )
    if helps:
        text += (
            f" Release one of {', '.join(f'{symbol}[{k}]' for k in helps)} from {fixed_name} "
            f"(each gives those rows a free {'coordinate' if level == 'q' else 'velocity'}), or "
            "drop the redundant constraints."
        )
    else:
        text += f" Remove entries from {fixed_name}, or drop the redundant constraints."
    return text


def _projection_message(system, q, position, velocity, rows, tolerance, fixed_q, fixed_qd, free_q, free_qd):
    """The error of an eager `consistent_initial_state`, or ``None`` if it succeeded."""
    jac, all_rows = (np.asarray(x) for x in rows)
    m_h = jac.shape[0]
    fixed_q = (fixed_q,) if isinstance(fixed_q, int) else tuple(fixed_q)
    fixed_qd = (fixed_qd,) if isinstance(fixed_qd, int) else tuple(fixed_qd)
    if system.holonomic is not None and not float(position) <= tolerance:
        if free_q is not None:
            text = _rows_without_free(jac, free_q, m_h, "q", fixed_q, "fixed_q")
            if text is not None:
                residual = float(position)
                return text + (
                    f" (The position residual stays at max |f| = {residual:.3g}.)"
                    if np.isfinite(residual)
                    else " (The projection is singular: it returns NaN.)"
                )
        return (
            position_failure_message(tolerance, np.asarray(q).dtype)
            + f" The residual after the Newton steps is max |f| = {float(position):.3g}"
            + f" at q = {np.asarray(q)}; the projection starts from the given q0, so a guess "
            "nearer the manifold may converge, or the constraints cannot all hold at once."
        )
    if free_qd is not None and not float(velocity) <= tolerance:
        text = _rows_without_free(all_rows, free_qd, m_h, "qd", fixed_qd, "fixed_qd")
        if text is not None:
            residual = float(velocity)
            return text + (
                f" (The velocity residual stays at max |(ḟ, g)| = {residual:.3g}.)"
                if np.isfinite(residual)
                else " (The projection is singular: it returns NaN.)"
            )
        return (
            "consistent_initial_state: the velocity constraints cannot hold with the velocities "
            f"in fixed_qd={fixed_qd} held at these values (residual max |(ḟ, g)| = "
            f"{float(velocity):.3g}): the held rates are incompatible with each other."
        )
    return None


def stages_for_forward_mode(solver, kind="lax"):
    """``solver`` with its Runge–Kutta stages scanned by ``lax`` (``scan_kind="lax"``), as
    forward-mode differentiation of a step needs (diffrax's default scan is checkpointed for
    reverse mode, which ``jax.jvp`` cannot go through). Other solvers are returned as they are."""
    # (A wrapper that does not forward ``scan_kind``, e.g. diffrax's HalfSolver, is left as it is.)
    if (
        isinstance(solver, (diffrax.AbstractRungeKutta, diffrax.AbstractSRK))
        and getattr(solver, "scan_kind", "unknown") is None
    ):
        solver = eqx.tree_at(lambda s: s.scan_kind, solver, kind, is_leaf=lambda x: x is None)
    return solver


def stages_for_adjoint(solver, adjoint):
    """The stage scan that diffrax's adjoints set on a Runge–Kutta solver they are handed
    (``"lax"`` for ``ForwardMode``, ``"bounded"`` for ``DirectAdjoint``; the others leave it),
    set here on ``solver`` itself: diffrax finds the solver by an ``isinstance`` check that sees
    through one wrapper, and jaxlag wraps user solvers twice (projection,
    `jaxlag._solver.step_once`)."""
    if isinstance(adjoint, diffrax.ForwardMode):
        return stages_for_forward_mode(solver)
    if isinstance(adjoint, diffrax.DirectAdjoint):
        return stages_for_forward_mode(solver, "bounded")
    return solver


def wrap_for_projection(solver, system, projection, adjoint, active=None):
    """``ProjectedSolver(solver, ...)``, made compatible with ``diffrax.ForwardMode``.

    ForwardMode needs Runge–Kutta stages scanned with ``scan_kind="lax"`` (it cannot differentiate
    the checkpointed scan in forward mode) and sets that itself on the solver it is handed; a
    wrapped solver hides the field, so it is set here on the inner solver.
    """
    if isinstance(adjoint, diffrax.ForwardMode):
        solver = stages_for_forward_mode(solver)
    return ProjectedSolver(solver, system, projection, active)
