r"""Equilibria and steady motions (relative equilibria) by a Newton root find.

An equilibrium, or a steady motion with constant velocities ``q̇*``, is a state with ``q̈ = 0``.
With ``M q̈ = F + Jᵀλ + Aᵀμ`` (sign convention of the library) that is the square system

    F(q, q̇*, t) + Jᵀλ + Aᵀμ = 0      (one row per coordinate not in ``fixed``)
    f(q, t) = 0                      (holonomic constraints)
    g(q, q̇*, t) = 0                  (velocity constraints)
    p_k(q, q̇*) = p_k*                (for each prescribed momentum, Routh's steady motion)

in the unknowns ``q`` (the coordinates not in ``fixed``), ``λ``, ``μ`` and the velocities
``q̇_k`` whose momenta are prescribed. It is solved with ``optimistix.root_find`` (Newton), so
the solution is differentiable (implicit function theorem) with respect to ``args`` and works
under ``jit`` and ``vmap``.

Steady motions are found in coordinates where the motion is a uniform drift of *cyclic*
coordinates: a circular orbit on a cone is ``r = r₀``, ``φ̇ = const`` in ``(r, φ)``. A cyclic
coordinate's own equation holds identically on such a motion and its value is arbitrary, so it
goes in ``fixed`` (held at its guessed value, its equation dropped). Its rate is either given in
``qd`` or found from a prescribed momentum (``momenta={index: value}``). After the solve every
``q̈``, ``f``, ``ḟ`` and ``g`` is checked, so a wrongly fixed coordinate is reported.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

from .. import _compile as compilation
from .._conventions import as_array_leaves, as_float_state
from .._custom_types import Args, Coordinates, RealScalarLike, Scalar, Vector, Velocities
from .._errors import compiled_check
from .._mechanics import constraints as _constraints
from .._mechanics import kkt as _kkt
from .._mechanics import lagrangian as _mechanics
from .._misc import is_concrete
from .._system import System

__all__ = ["Equilibrium", "equilibrium"]


class Equilibrium(eqx.Module):
    """The result of `equilibrium`.

    - ``q``, ``qd``: the equilibrium (or steady-motion) state.
    - ``multipliers``, ``velocity_multipliers``: ``λ``, ``μ`` holding it (``F + Jᵀλ + Aᵀμ = 0``).
    - ``accelerations``: ``q̈`` recomputed there (≈ 0).
    - ``residual``: max-norm of the row-scaled residual of the equations above.
    - ``result``: ``optimistix.RESULTS`` of the root find; ``num_steps``: Newton steps taken.
    """

    q: Vector
    qd: Vector
    multipliers: Float[Array, " m_h"]
    velocity_multipliers: Float[Array, " m_v"]
    accelerations: Vector
    residual: Scalar
    result: optx.RESULTS
    num_steps: Int[Array, ""]


def _indices(spec, n, name):
    if spec is None:
        return ()
    if isinstance(spec, (int, np.integer)):
        spec = (spec,)
    out = []
    for i in spec:
        i = int(i)
        if not -n <= i < n:
            raise ValueError(f"{name} index {i} is out of range for {n} coordinates.")
        out.append(i % n)
    if len(set(out)) != len(out):
        raise ValueError(f"{name} has repeated indices: {tuple(spec)}.")
    return tuple(sorted(out))


class _Layout(eqx.Module):
    """Static bookkeeping: which coordinates and velocities are unknowns."""

    n: int = eqx.field(static=True)
    free: tuple = eqx.field(static=True)
    momentum_indices: tuple = eqx.field(static=True)
    m_h: int = eqx.field(static=True)
    m_v: int = eqx.field(static=True)

    def split(self, z):
        k, j = len(self.free), len(self.momentum_indices)
        return (z[:k], z[k : k + j], z[k + j : k + j + self.m_h], z[k + j + self.m_h :])

    def state(self, z, q0, qd0):
        q_free, qd_free, _, _ = self.split(z)
        q = q0.at[jnp.asarray(self.free, int)].set(q_free) if self.free else q0
        if self.momentum_indices:
            qd0 = qd0.at[jnp.asarray(self.momentum_indices, int)].set(qd_free)
        return q, qd0


def _residual(z, data):
    system, layout, q0, qd0, t, args, target, scale = data
    q, qd = layout.state(z, q0, qd0)
    _, _, lam, mu = layout.split(z)
    _, force = _mechanics.mass_and_forces(system, q, qd, t, args)
    parts = []
    total = force
    if layout.m_h:
        jac = jax.jacfwd(lambda x: _constraints.holonomic_residual(system, x, t, args))(q)
        total = total + jac.T @ lam
    if layout.m_v:
        _, a, _ = _constraints.velocity_terms(system, q, qd, t, args)
        total = total + a.T @ mu
    if layout.free:
        parts.append(total[jnp.asarray(layout.free, int)])
    if layout.m_h:
        parts.append(_constraints.holonomic_residual(system, q, t, args))
    if layout.m_v:
        parts.append(_constraints.velocity_residual(system, q, qd, t, args))
    if layout.momentum_indices:
        p = _mechanics.momenta(system, q, qd, t, args)
        parts.append(p[jnp.asarray(layout.momentum_indices, int)] - target)
    out = jnp.concatenate(parts)
    return out if scale is None else out / scale


def _static_multipliers(system, layout, q, qd, t, args):
    """Least-squares ``Λ`` of ``F + GᵀΛ ≈ 0`` at the guess (exact at an equilibrium)."""
    m = layout.m_h + layout.m_v
    if m == 0:
        return jnp.zeros((0,), q.dtype)
    _, force = _mechanics.mass_and_forces(system, q, qd, t, args)
    rows = []
    if layout.m_h:
        rows.append(jax.jacfwd(lambda x: _constraints.holonomic_residual(system, x, t, args))(q))
    if layout.m_v:
        rows.append(_constraints.velocity_terms(system, q, qd, t, args)[1])
    g = jnp.concatenate(rows)
    return -jnp.linalg.solve(g @ g.T, g @ force)


@compilation.lean_jit
def _solve(system, q0, qd0, t, args, target, layout, solver, max_steps, tolerance):
    if layout.momentum_indices:
        # Start the unknown velocities on the prescribed momenta at the guessed q: one Newton
        # step in q̇_K, exact because p = ∂L/∂q̇ is affine in q̇ for a mechanical Lagrangian.
        idx = jnp.asarray(layout.momentum_indices, int)

        def momentum_residual(v):
            return _mechanics.momenta(system, q0, qd0.at[idx].set(v), t, args)[idx] - target

        v0 = qd0[idx]
        v0 = v0 - jnp.linalg.solve(jax.jacfwd(momentum_residual)(v0), momentum_residual(v0))
        qd0 = qd0.at[idx].set(v0)
    multipliers0 = _static_multipliers(system, layout, q0, qd0, t, args)
    z0 = jnp.concatenate(
        [
            q0[jnp.asarray(layout.free, int)] if layout.free else jnp.zeros((0,), q0.dtype),
            qd0[jnp.asarray(layout.momentum_indices, int)]
            if layout.momentum_indices
            else jnp.zeros((0,), q0.dtype),
            multipliers0,
        ]
    )
    # Equilibrate the rows (their units differ: forces, lengths, momenta) by the row norms of the
    # Jacobian at the guess, so that Newton's test |residual| < atol reads "the next step is below
    # atol" in every row. A constant scale does not move the root; its gradient is cut so that
    # implicit differentiation sees the plain equations.
    jac0 = jax.jacfwd(_residual)(z0, (system, layout, q0, qd0, t, args, target, None))
    scale = jax.lax.stop_gradient(jnp.linalg.norm(jac0, axis=1))
    scale = jnp.where(scale > 0, scale, 1.0)
    data = (system, layout, q0, qd0, t, args, target, scale)
    solution = optx.root_find(_residual, solver, z0, data, max_steps=max_steps, throw=False)
    z = solution.value
    q, qd = layout.state(z, q0, qd0)
    _, _, lam, mu = layout.split(z)
    qdd = _kkt.accelerations_and_multipliers(system, q, qd, t, args)[0]
    residual = jnp.max(jnp.abs(_residual(z, data)), initial=0.0)
    mass, force = _mechanics.mass_and_forces(system, q, qd, t, args)
    # Size of the terms that cancel in M q̈ = F + Gᵀ Λ, as accelerations: the yardstick for "q̈ ≈ 0".
    accel_scale = jnp.max(jnp.abs(jnp.linalg.solve(mass, force)), initial=0.0)
    f, f_dot, g = _constraints.constraint_residuals(system, q, qd, t, args)
    if layout.momentum_indices:
        p = _mechanics.momenta(system, q, qd, t, args)[jnp.asarray(layout.momentum_indices, int)]
        momentum_error = jnp.max(jnp.abs(p - target) / (1.0 + jnp.abs(target)))
    else:
        momentum_error = jnp.zeros((), q.dtype)
    checks = dict(
        finite=jnp.all(jnp.isfinite(z)) & jnp.all(jnp.isfinite(qdd)),
        steady=jnp.max(jnp.abs(qdd), initial=0.0) <= tolerance * (1.0 + accel_scale),
        on_manifold=jnp.max(
            jnp.concatenate([jnp.abs(f), jnp.abs(f_dot), jnp.abs(g), jnp.zeros((1,), q.dtype)])
        )
        <= tolerance,
        momenta=momentum_error <= tolerance,
        f=f,
        f_dot=f_dot,
        g=g,
    )
    # Newton's residual test can fail to be met when the iteration starts at the root to rounding
    # (the residual cannot drop below the rounding of the cancelling terms); the state decides.
    solved = (
        checks["finite"]
        & checks["momenta"]
        & checks["on_manifold"]
        & ((solution.result == optx.RESULTS.successful) | checks["steady"])
    )
    result = optx.RESULTS.where(solved, optx.RESULTS.successful, solution.result)
    return Equilibrium(q, qd, lam, mu, qdd, residual, result, solution.stats["num_steps"]), checks


def equilibrium(
    system: System,
    q: Coordinates,
    qd: Velocities | None = None,
    t: RealScalarLike = 0.0,
    args: Args = None,
    *,
    fixed: int | Sequence[int] = (),
    momenta: dict[int, RealScalarLike] | None = None,
    solver: optx.AbstractRootFinder | None = None,
    max_steps: int = 64,
    tolerance: float = 1e-8,
    throw: bool = True,
) -> Equilibrium:
    r"""Find an equilibrium or a steady motion of ``system`` near the guess ``q``.

    **Arguments:**

    - ``q``: initial guess for the coordinates (n,).
    - ``qd``: the constant velocities of a steady motion (default: rest, all zero).
    - ``t``, ``args``: time and parameters, as everywhere in jaxlag.
    - ``fixed``: indices of coordinates held at their values in ``q`` whose equations are
      dropped: the cyclic coordinates of a steady motion (their equations hold identically
      there, and their values are arbitrary, so Newton's matrix would be singular otherwise).
    - ``momenta``: ``{index: p}`` prescribes the momentum ``p_k = ∂L/∂q̇_k`` and makes
      ``q̇_k`` an unknown (guess taken from ``qd``): a circular orbit of given angular momentum.
    - ``solver``: an ``optimistix`` root finder (default ``optx.Newton(rtol=1e-12, atol=1e-12)``
      on row-equilibrated equations). If it stops short of its own tolerance (e.g. started at
      the root to rounding) the state checks below decide.
    - ``tolerance``: after the solve, ``|q̈|`` must be below ``tolerance`` times the size of the
      cancelling terms ``|M⁻¹F|`` (plus ``tolerance``), and ``|f|, |ḟ|, |g|`` below
      ``tolerance``.
    - ``throw``: raise if the solve fails or the checks do not pass (``ValueError`` outside
      transformations, an ``eqx.error_if`` runtime error under ``jit``). With ``throw=False``
      inspect ``result`` and ``residual``.

    Returns an `Equilibrium`. Differentiable with respect to ``args`` by implicit
    differentiation of the root find (``jax.grad`` of, e.g., an orbit radius with respect to a
    mass). The equations are square only if the equilibrium is isolated; families of equilibria
    (a free particle, a nonholonomic system at rest) need more coordinates in ``fixed``.
    """
    q, qd = as_float_state(q, jnp.zeros_like(jnp.asarray(q)) if qd is None else qd)
    qd = qd.astype(q.dtype)
    args = as_array_leaves(args, q.dtype)  # new parameter values must not recompile
    system.check(q, qd, t, args)
    n = q.shape[0]
    fixed = _indices(fixed, n, "fixed")
    momenta = dict(momenta or {})
    momentum_indices = _indices(tuple(momenta), n, "momenta")
    momenta = {int(k) % n: v for k, v in momenta.items()}
    target = (
        jnp.stack([jnp.asarray(momenta[k], q.dtype) for k in momentum_indices])
        if momentum_indices
        else jnp.zeros((0,), q.dtype)
    )
    free = tuple(i for i in range(n) if i not in fixed)
    m_h = system.num_holonomic(q, t, args)
    m_v = 0
    if system.velocity_constraints is not None:
        m_v = jax.eval_shape(lambda a, b: _constraints.velocity_residual(system, a, b, t, args), q, qd).shape[
            0
        ]
    unknowns = len(free) + len(momentum_indices) + m_h + m_v
    if unknowns == 0:
        raise ValueError("equilibrium: nothing to solve for (every coordinate is fixed).")
    layout = _Layout(n, free, momentum_indices, m_h, m_v)
    if solver is None:
        solver = optx.Newton(rtol=1e-12, atol=1e-12)
    t = jnp.asarray(t, q.dtype)
    eq, checks = _solve(system, q, qd, t, args, target, layout, solver, max_steps, tolerance)
    if not throw:
        return eq
    failed = eq.result != optx.RESULTS.successful
    not_steady = ~checks["steady"]
    if is_concrete((q, qd, t, args, eq.q)):
        if bool(checks["finite"]) and not bool(checks["on_manifold"]):
            raise ValueError(
                "equilibrium: no solution on the constraint manifold: at the last iterate "
                f"q = {np.asarray(eq.q)}, qd = {np.asarray(eq.qd)}: f = {np.asarray(checks['f'])}, "
                f"ḟ = {np.asarray(checks['f_dot'])}, g = {np.asarray(checks['g'])}. Are the "
                "velocities qd compatible with the constraints (J q̇ + ∂f/∂t = 0, A q̇ + b = 0)?"
            )
        if bool(failed):
            raise ValueError(
                f"equilibrium: the root find did not converge ({eq.result}) in {int(eq.num_steps)} "
                f"of max_steps={max_steps} steps from the guess q = {np.asarray(q)}, "
                f"qd = {np.asarray(qd)}; last iterate q = {np.asarray(eq.q)}, residual "
                f"{float(eq.residual):.3g}. Try a closer guess. If the equilibrium is not isolated "
                "(a cyclic coordinate, a family of equilibria), hold those coordinates with "
                "`fixed=`; if none exists (e.g. no steady motion at these velocities) there is "
                "nothing to find."
            )
        if bool(not_steady):
            raise ValueError(
                "equilibrium: the equations solved, but the state is not steady: q̈ = "
                f"{np.asarray(eq.accelerations)} at q = {np.asarray(eq.q)}, qd = {np.asarray(eq.qd)}. "
                f"A coordinate in fixed={fixed} is not cyclic (its own equation does not hold "
                "by itself); fix only coordinates the Lagrangian does not depend on."
            )
        return eq
    q_out = compiled_check(
        eq.q,
        failed | not_steady,
        jnp.where(failed, 0, 1),
        (
            "jaxlag.analysis.equilibrium: the root find did not converge (or its solution is "
            "off the constraint manifold); try a closer guess, or fix the coordinates "
            "of a non-isolated equilibrium (`fixed=`).",
            "jaxlag.analysis.equilibrium: the solution is not steady (q̈ ≠ 0): a coordinate in "
            "`fixed` is not cyclic.",
        ),
    )
    return eqx.tree_at(lambda e: e.q, eq, q_out)
