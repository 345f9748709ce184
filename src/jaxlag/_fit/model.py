r"""The model: free variables -> weighted residuals, and their linearization.

Experiment ``e`` observed at save time ``t_i`` is modelled as
``y_e(t_i) = observe(q(t_i), q̇(t_i), t_i, args)`` with ``(q, q̇)`` from [`simulate`][jaxlag.simulate]
and ``args = {**fixed_args, **params}``; the residuals are ``r = (y_model − y_observed) / σ``
(zero where the observation is NaN), followed with multiple shooting by the continuity residuals
``w (x_end(segment k) − x_start(segment k+1))``.
"""

from typing import Any, Literal, overload

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from .. import _compile as compilation
from .. import _diagnosis
from .. import _errors as failures
from .._checks import Checks
from .._conventions import as_jax_array
from .._errors import FailureCode
from .._mechanics import constraints as _constraints
from .._mechanics.lagrangian import as_time, mass_solver
from .._misc import is_concrete
from .._simulate import simulate
from .._stabilization import (
    _schur_correction,
    consistent_initial_state,
    default_projection_tolerance,
    position_failure_message,
    project_state,
    projection_with_residuals,
)
from .data import Data
from .options import Identity


class ParamSpec(eqx.Module):
    """Static description of the parameter dict, so repeated fits reuse compiled code.

    `ravel` and `unravel` of known values (NumPy or JAX arrays outside a trace) work on the
    host: eager ``jax.numpy`` would compile a small program for each operation."""

    keys: tuple = eqx.field(static=True)
    shapes: tuple = eqx.field(static=True)

    def ravel(self, params):
        if is_concrete(params):
            return as_jax_array(np.concatenate([np.ravel(np.asarray(params[k])) for k in self.keys]))
        return jnp.concatenate([jnp.ravel(params[k]) for k in self.keys])

    def unravel(self, flat):
        concrete = is_concrete(flat)
        if concrete:
            flat = np.asarray(flat)
        out, i = {}, 0
        for k, shape in zip(self.keys, self.shapes):
            size = int(np.prod(shape))
            out[k] = flat[i : i + size].reshape(shape)
            out[k] = as_jax_array(out[k]) if concrete else out[k]
            i += size
        return out


class Model(eqx.Module):
    """Maps the free variables to residuals; holds everything static about the fit.

    Free variables: ``{"params": flat unconstrained parameters}`` plus, when the initial state is
    estimated, ``"states"`` (all segment states), or with multiple shooting alone ``"later"``
    (the states of segments 1..S−1; segment 0 starts from the known initial state).
    """

    system: Any
    observe: Any
    transforms: Any
    spec: ParamSpec
    segments: int = eqx.field(static=True)
    estimate_initial_state: bool = eqx.field(static=True)
    # The options of jl.simulate (a SimulateOptions), forwarded untouched. Under the fit's
    # filter_jit their Python numbers are part of the cache key, so a second fit with equal
    # options reuses the compiled programs, and array-valued options are traced.
    simulation: dict[str, Any]
    periodic: tuple = eqx.field(static=True, default=())
    # Partial estimation: the indices of the estimated entries of (q0, qd0); None = all.
    initial_mask: tuple[tuple[int, ...], tuple[int, ...]] | None = eqx.field(static=True, default=None)

    def simulate(self, q0, qd0, ts, args, **kwargs):
        """[`simulate`][jaxlag.simulate] of the system with the fit's simulation options."""
        return simulate(self.system, q0, qd0, ts, args=args, **self.simulation, **kwargs)

    def physical(self, flat):
        """``θ = to_physical(u)`` of each parameter, from the flat unconstrained ``u``."""
        params = self.spec.unravel(flat)
        return {k: self.transforms.get(k, Identity()).to_physical(v) for k, v in params.items()}

    def unconstrained(self, physical):
        """The flat ``u = to_unconstrained(θ)``, the inverse of `physical`."""
        return self.spec.ravel(
            {k: self.transforms.get(k, Identity()).to_unconstrained(v) for k, v in physical.items()}
        )

    def split(self, states):
        """Free part of the segment states, and the fixed part."""
        if self.estimate_initial_state and self.initial_mask is not None:
            qi, qdi = (list(i) for i in self.initial_mask)
            free = {"initial": (states[0][:, 0][:, qi], states[1][:, 0][:, qdi])}
            if self.segments > 1:
                free["later"] = (states[0][:, 1:], states[1][:, 1:])
            return free, (states[0][:, :1], states[1][:, :1])
        if self.estimate_initial_state:
            return {"states": states}, None
        if self.segments > 1:
            return {"later": (states[0][:, 1:], states[1][:, 1:])}, (states[0][:, :1], states[1][:, :1])
        return {}, states

    def states(self, free, fixed_states):
        """The segment states ``(q, qd)``, (E, S, n) each, from their free and fixed parts."""
        if self.estimate_initial_state and self.initial_mask is not None:
            qi, qdi = (list(i) for i in self.initial_mask)
            first = (
                fixed_states[0].at[:, 0, qi].set(free["initial"][0]),
                fixed_states[1].at[:, 0, qdi].set(free["initial"][1]),
            )
            if self.segments == 1:
                return first
            return (
                jnp.concatenate([first[0], free["later"][0]], axis=1),
                jnp.concatenate([first[1], free["later"][1]], axis=1),
            )
        if self.estimate_initial_state:
            return free["states"]
        if self.segments > 1:
            return (
                jnp.concatenate([fixed_states[0], free["later"][0]], axis=1),
                jnp.concatenate([fixed_states[1], free["later"][1]], axis=1),
            )
        return fixed_states

    def observations_of(self, params, data: Data, states, adjoint, health=False):
        """The observations of every segment, their end states, and (``health=True``) what the
        host must check afterwards instead of checks compiled into the program: the simulation
        failure records and the residual of the initial-state projection, shape (E, S) each.
        The save times were checked on the host (``fit`` checks its data once)."""
        args = {**data.fixed, **params}

        def one_segment(ts, q0, qd0):
            kwargs = {}
            residual = jnp.zeros((), q0.dtype)
            if self.system.is_constrained:
                if health:
                    q0, qd0, residual = _projection_with_residual(self.system, q0, qd0, ts[0], args)
                else:
                    q0, qd0 = consistent_initial_state(self.system, q0, qd0, ts[0], args)
            if health:  # projected states are on the manifold: the failure record covers the rest
                kwargs.update(throw=False, checks=Checks(initial_state=False, times=False))
            traj = self.simulate(q0, qd0, ts, args, adjoint=adjoint, **kwargs)
            y = jax.vmap(lambda q, qd, t: self.observe(q, qd, t=t, args=args))(traj.q, traj.qd, ts)
            return y, traj.q[-1], traj.qd[-1], (traj.failure, residual)

        # states: (E, S, n) each; ts_seg: (E, S, m + 1)
        if data.ts_seg.shape[:2] == (1, 1):
            # One experiment, one segment: no batching transform of the solver (its fixpoints
            # over diffrax's loops are most of the tracing time of the least-squares program).
            out = one_segment(data.ts_seg[0, 0], states[0][0, 0], states[1][0, 0])
            y, q_end, qd_end, checks = jax.tree.map(lambda x: jnp.asarray(x)[None, None], out)
        else:
            y, q_end, qd_end, checks = jax.vmap(jax.vmap(one_segment))(data.ts_seg, states[0], states[1])
        return (y, q_end, qd_end, checks) if health else (y, q_end, qd_end)

    @overload
    def residuals(self, free, data, fixed_states, adjoint, health: Literal[False] = False) -> jax.Array: ...
    @overload
    def residuals(self, free, data, fixed_states, adjoint, health: Literal[True]) -> tuple[Any, Any]: ...
    def residuals(self, free, data, fixed_states, adjoint, health: bool = False) -> Any:
        """The weighted residuals ``r = (y_model − y_observed) / σ`` (0 where the observation is
        NaN), then with multiple shooting ``w (x_end(k) − x_start(k+1))`` (angles of periodic
        coordinates wrapped into [−π, π)); with ``health=True`` also the checks of
        `observations_of` (the host raises with `raise_for_health`)."""
        params = self.physical(free["params"])
        states = self.states(free, fixed_states)
        y, q_end, qd_end, *checks = self.observations_of(params, data, states, adjoint, health)
        # Stitch segments back to the save grid: drop each later segment's first (shared) point.
        e = y.shape[0]
        rest = y[:, 1:, 1:].reshape(e, -1, y.shape[-1])
        y = jnp.concatenate([y[:, 0], rest], axis=1)
        observed = data.observations
        mask = jnp.isfinite(observed)
        r = jnp.where(mask, (y - jnp.where(mask, observed, 0.0)) / data.noise, 0.0)
        pieces = [r.ravel()]
        if self.segments > 1:
            w = data.continuity_weight
            gap = q_end[:, :-1] - states[0][:, 1:]
            if self.periodic:
                # Angles meet modulo 2π: wrap the gap of periodic coordinates into [−π, π).
                index = jnp.asarray(self.periodic)
                wrapped = jnp.mod(gap[..., index] + jnp.pi, 2 * jnp.pi) - jnp.pi
                gap = gap.at[..., index].set(wrapped)
            pieces.append((w * gap).ravel())
            pieces.append((w * (qd_end[:, :-1] - states[1][:, 1:])).ravel())
        r = jnp.concatenate(pieces)
        return (r, checks[0]) if health else r


def _projection_with_residual(system, q0, qd0, t0, args, newton_steps: int = 20):
    """``(q, qd, max |f(q)|)``: `projection_with_residuals` (the projection of
    `consistent_initial_state`, its checks left to the host) with the Newton iterations of the
    positions in one loop of the program instead of ``newton_steps`` copies of them: the same
    iterations (the metric ``M`` at the incoming state, held fixed), then the velocities
    projected with ``M`` at the corrected positions, as ``project_state`` does. Unrolled, the
    iterations were a third of the fit's Jacobian program and of its tracing time (the
    constraint function and its Jacobian traced, differentiated and batched 20 times)."""
    if system.holonomic is None:
        q, qd, position, _ = projection_with_residuals(system, q0, qd0, t0, args, newton_steps)
        return q, qd, position
    t = as_time(t0, q0)
    solve_mass = mass_solver(system, q0, qd0, t, args)

    def newton(_, q):
        f = _constraints.holonomic_residual(system, q, t, args)
        jac = _constraints.holonomic_jacobian(system, q, t, args, f.shape[0])
        return q - _schur_correction(system, solve_mass, jac, f)

    q = jax.lax.fori_loop(0, newton_steps, newton, q0)
    # No Newton step left: the velocity projection with M factored at the corrected q.
    q, qd = project_state(system, q, qd0, t, args, newton_steps=0)
    position = jnp.max(jnp.abs(_constraints.holonomic_residual(system, q, t, args)), initial=0.0)
    return q, qd, position


class Problem(eqx.Module):
    """What the loops and the statistics work on: the ``model``, the ``data``, the starting
    free variables ``free`` and the fixed part of the segment states (see `Model.split`)."""

    model: Model
    data: Data
    free: dict[str, Any]
    fixed_states: Any


class Linearization(eqx.Module):
    """The residuals linearized at ``y₀``: ``r(y) ≈ r + J (y − y₀)``, with ``y`` the free variables
    raveled (``jax.flatten_util.ravel_pytree`` order)."""

    residuals: Float[Array, " N"]
    jacobian: Float[Array, "N m"]
    point: Float[Array, " m"]


#: The most work per call for which the fit linearizes with its lean program (`_linearize_lean`):
#: integrator steps × (free scalars + 1) × coordinates², summed over the experiments and the
#: shooting segments. The README demo's fit does about 530 per call (44 steps, 2 free scalars,
#: 2 coordinates): 1 ms per call optimized, 2.5–3.5 ms lean, and the lean program compiles 1.4 s
#: sooner (2-core CPU, one pinned core). At 2,500 (≈ 5 ms optimized, ≈ 15 ms lean) twenty calls
#: still cost less than the compile time saved; the multiple-shooting double pendulum of
#: ``examples/fit_double_pendulum.py`` (16 segments, 62 free scalars) does ~10⁵ and takes
#: 0.28 s per call optimized, 0.62 s without LLVM's optimizations.
LEAN_WORK = 2500


class Linearizer:
    """The residuals and their Jacobian at the trial points of one fit, from one of two programs
    that compute the same thing (`_linearize`, `_linearize_lean`), chosen by the size of the fit.

    A fit starts with the lean program when its size says that a call is cheap: the save times
    (for the integrator steps, with room for 4× more) × (free scalars + 1) × coordinates² summed
    over the experiments and segments at most ``4 × LEAN_WORK``. After each lean call the steps
    the integrator took are known (the failure record counts them): from the first call whose
    work exceeds `LEAN_WORK` on, the fit uses the optimized program. The choice depends only on
    the fit's inputs, never on timings: the same script gives the same numbers. (The two
    programs agree to rounding: they push the tangents in another order and XLA optimizes
    them differently.)
    """

    def __init__(self, model: Model, data: Data, fixed_states, free, lean: bool | None = None):
        self.model, self.data, self.fixed_states = model, data, fixed_states
        self.size = sum(int(np.size(leaf)) for leaf in jax.tree.leaves(free))
        states = fixed_states if fixed_states is not None else free["states"]
        self.n = int(np.shape(states[0])[-1])
        if lean is None:
            experiments, segments, points = np.shape(data.ts_seg)
            lean = experiments * segments * points * self._per_step() <= 4 * LEAN_WORK
        self.lean = lean

    def _per_step(self) -> int:
        return (self.size + 1) * self.n**2

    def __call__(self, free) -> Linearization:
        program = _linearize_lean if self.lean else _linearize
        linearization, checks = program(self.model, free, self.data, self.fixed_states)
        checks = jax.device_get(checks)
        raise_for_health(self.model, checks, free["params"], self.data)
        if self.lean and int(np.sum(checks[0].num_steps, dtype=np.int64)) * self._per_step() > LEAN_WORK:
            self.lean = False  # the calls are not cheap: the optimized program from now on
        return linearization


def residuals_and_jacobian(
    model: Model, free, data: Data, fixed_states, lean: bool | None = None
) -> Linearization:
    """The residuals at the free variables ``free`` and their Jacobian ``J = ∂r/∂y``.

    Forward mode, one tangent per free scalar. This is the one large program of a
    least-squares fit: the optimizer's own step only sees the linear model built from it. Its
    checks (a failed simulation, an initial state that cannot be projected) are returned and
    raised here, on the host: the program has no host callback, so JAX's persistent cache
    stores it. ``lean``: which program (`Linearizer`; None: chosen by the size of the fit).
    """
    return Linearizer(model, data, fixed_states, free, lean)(free)


def _linearization(model, free, data, fixed_states, batched: bool):
    flat, unravel = ravel_pytree(free)

    def residuals(y):
        return model.residuals(unravel(y), data, fixed_states, diffrax.ForwardMode(), health=True)

    def push(direction):
        return jax.jvp(residuals, (flat,), (direction,), has_aux=True)

    if flat.shape[0] == 1:  # one free variable: a plain jvp, no size-1 batch of the solver
        r, column, checks = push(jnp.ones_like(flat))
        return Linearization(r, column[:, None], flat), checks
    directions = jnp.eye(flat.shape[0], dtype=flat.dtype)
    if batched:
        r, columns, checks = jax.vmap(push, out_axes=(None, 0, None))(directions)
    else:
        r, columns, checks = jax.lax.map(push, directions)
        r, checks = jax.tree.map(lambda x: x[0], (r, checks))
    return Linearization(r, columns.T, flat), checks


@compilation.filter_jit
def _linearize(model, free, data, fixed_states):
    """`residuals_and_jacobian` optimized for run time: the tangents of all free scalars pushed
    at once (``vmap`` of ``jvp``: the primal solve runs once), with XLA's full optimizations."""
    return _linearization(model, free, data, fixed_states, batched=True)


@compilation.lean_jit
def _linearize_lean(model, free, data, fixed_states):
    """`residuals_and_jacobian` for a fit whose calls are cheap, compiled for the time to the first
    result: one tangent at a time (``lax.map`` of ``jvp``, traced once: the batching of diffrax's
    loops was half the tracing of `_linearize`), without LLVM's optimizations on the CPU
    (`lean_jit`). The README demo's fit: tracing and lowering 1.16 → 0.60 s, XLA 2.10 → 1.23 s;
    run time 1 ms → 2.5–3.5 ms per call."""
    return _linearization(model, free, data, fixed_states, batched=False)


def raise_for_health(model: Model, checks, flat_params, data: Data) -> None:
    """Raise what the checks of `Model.observations_of` found (host side): an initial
    state the projection could not bring onto the constraint manifold (``ValueError``, as
    [`consistent_initial_state`][jaxlag.consistent_initial_state]), or a failed simulation
    (``SimulationError``, with
    the diagnosis at the parameters being tried)."""
    failure, residual = jax.device_get(checks)
    residual = np.asarray(residual)
    tolerance = default_projection_tolerance(residual.dtype)

    def where(index):
        return (
            f"experiment {index[0]}"
            if model.segments == 1
            else f"experiment {index[0]}, shooting segment {index[1]}"
        )

    bad = np.argwhere(~(residual <= tolerance))
    if bad.size:
        raise ValueError(
            f"jl.fit, {where(tuple(bad[0]))}: " + position_failure_message(tolerance, residual.dtype)
        )
    failed = np.argwhere(np.asarray(failure.code) != FailureCode.COMPLETED)
    if failed.size:
        index = tuple(failed[0])
        params = model.physical(flat_params)  # only now: eager operations compile
        args = jax.device_get({**data.fixed, **params})
        text = _diagnosis.describe(_diagnosis.member(failure, index), model.system, args)
        raise failures.SimulationError(
            f"jl.fit, {where(index)}, at parameters "
            + ", ".join(f"{k}={np.asarray(v)}" for k, v in params.items())
            + ": "
            + text
        )


@compilation.filter_jit
def guess_states(model: Model, ts, q0, qd0, args, starts):
    """The segment states of a simulation with the starting parameters, (E, S, n) each."""
    guess = jax.vmap(lambda t, a, b: model.simulate(a, b, t, args))(ts, q0, qd0)
    return guess.q[:, starts], guess.qd[:, starts]


def unconstrained(model: Model, params):
    """The free parameters (raveled, unconstrained) of the physical ``params``: on the host for
    known values (no program is compiled for them)."""
    return model.unconstrained(params)
