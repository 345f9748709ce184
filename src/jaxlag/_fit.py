r"""System identification: fit parameters (and initial states) to observed trajectories.

The model of experiment ``e`` at save time ``t_i`` is ``y_e(t_i) = observe(q(t_i), q̇(t_i), t_i, args)``
where ``(q, q̇)`` comes from :func:`~jaxlag.simulate` with ``args = {**fixed_args, **params}``.
The fit minimizes the least-squares loss

    ℓ(θ) = ½ Σ_{e,i,k} r_{eik}²,     r = (y_model − y_observed) / σ

over the free parameters ``θ`` (optionally through a reparameterization, e.g. ``θ = exp(u)`` for
positive parameters), where NaN observations are masked out (they contribute no residual).

Two kinds of optimizer (``optimizer=``):

* an optimistix Gauss–Newton-type least-squares solver (``optx.LevenbergMarquardt``, the default,
  ``optx.GaussNewton``, ``optx.Dogleg``, ``optx.IndirectLevenbergMarquardt``: the subclasses of
  ``optx.AbstractGaussNewton``), which carries its own ``rtol``/``atol``. The Jacobian of the
  residuals is built in forward mode (``diffrax.ForwardMode``), one tangent per parameter, which
  for a handful of parameters is far cheaper than reverse mode.
* any ``optax.GradientTransformation``: gradient descent on ``ℓ`` with ``jax.value_and_grad``
  through the simulation (the default :class:`~jaxlag.ForwardSensitivities`: forward
  sensitivities for up to 10 free scalars, else ``diffrax.RecursiveCheckpointAdjoint``).

Standard errors come from the Gauss–Newton approximation at the optimum: with the Jacobian
``J = ∂r/∂θ`` in physical parameters, ``Cov = σ̂² (JᵀJ)⁻¹``, where ``σ̂² = |r|²/(N − p)`` is
estimated from the residuals unless ``noise_std`` is given (then ``Cov = (JᵀJ)⁻¹``). The
inverse is rank-revealing (an SVD of ``J`` with its columns scaled to unit norm, singular
values below ``√ε · s_max`` dropped): a parameter along a direction the data cannot determine,
or one that does not affect the residuals, gets an infinite standard error, its name in
``FitResult.undetermined`` / ``FitResult.insensitive``, and a :class:`FitWarning` that says
which combination is determined (``only g/l is determined by the data``). The fit also warns
when a parameter ends at a :class:`Bounded` bound, and, with ``noise_std`` given, when the
reduced χ² exceeds ``1 + 5 √(2/(N − p))`` (five standard deviations of the χ² distribution
above its mean: a local minimum, or a model that does not describe the data).

Chaotic or long trajectories: ``shooting=Shooting(segments=S)`` splits each experiment into
``S`` segments, each starting from its own free state, and adds continuity residuals
``w (x_end(segment k) − x_start(segment k+1))`` (multiple shooting).
"""

from __future__ import annotations

import operator
import warnings
from collections.abc import Callable, Sequence
from typing import Any, Literal, cast, overload

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float

from . import _compile as compilation
from ._custom_types import Coordinates, RealScalarLike, SaveTimes, Scalar, Velocities
from ._conventions import wrap_state_function
from ._adjoint import ForwardSensitivities
from ._misc import is_concrete
from ._checks import Checks
from ._simulate import simulate
from ._system import System
from . import _errors as failures
from ._stabilization import (
    Baumgarte,
    Projection,
    consistent_initial_state,
    default_projection_tolerance,
    position_failure_message,
    projection_with_residuals,
)


# ----------------------------------------------------------------------------- reparameterization
class Identity(eqx.Module):
    """No reparameterization: ``θ = u``."""

    def to_physical(self, u):
        return u

    def to_unconstrained(self, p):
        return p


class Positive(eqx.Module):
    """Positive parameter: ``θ = exp(u)``."""

    def to_physical(self, u: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        return jnp.exp(u)

    def to_unconstrained(self, p: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        return jnp.log(p)


class Bounded(eqx.Module):
    """Parameter in ``(lower, upper)``: ``θ = lower + (upper − lower) sigmoid(u)``."""

    lower: float
    upper: float

    def to_physical(self, u: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        return self.lower + (self.upper - self.lower) * jax.nn.sigmoid(u)

    def to_unconstrained(self, p: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
        s = (p - self.lower) / (self.upper - self.lower)
        return jnp.log(s) - jnp.log1p(-s)


# ----------------------------------------------------------------------------- options
#: ``q`` or ``q̇`` of every shooting segment's starting state, one row per experiment and segment.
SegmentStates = Float[Array, "experiments segments n"]


def _index_tuple(indices) -> tuple:
    return tuple(operator.index(i) for i in indices)  # ints only: a float index is a TypeError


def _state_pair(states):
    return None if states is None else tuple(states)


class Shooting(eqx.Module):
    """Multiple shooting, the ``shooting=`` option of :func:`fit`.

    - ``segments``: each experiment is split into this many segments (it must divide
      ``len(ts) − 1``; segments share their boundary save times), each starting from its own
      free state. ``1`` (the default) is single shooting.
    - ``continuity_weight``: the weight ``w > 0`` of the continuity residuals
      ``w (x_end(segment k) − x_start(segment k+1))``.
    - ``states``: optional ``(q, qd)`` of shape (E, S, n) each, the starting guesses of the
      segment states (default: a simulation with the starting parameters).
    - ``periodic_coordinates``: indices of angle coordinates whose continuity gaps are taken
      modulo 2π (so segment states may be given in any branch, e.g. from inverse kinematics).
    """

    segments: int = 1
    continuity_weight: RealScalarLike = 10.0
    states: (
        tuple[Float[ArrayLike, "experiments segments n"], Float[ArrayLike, "experiments segments n"]] | None
    ) = eqx.field(default=None, converter=_state_pair)
    periodic_coordinates: tuple[int, ...] = eqx.field(default=(), converter=_index_tuple)

    def __check_init__(self):
        if isinstance(self.segments, bool) or not isinstance(self.segments, (int, np.integer)):
            raise TypeError(f"Shooting(segments=...) must be an int; got {self.segments!r}.")
        if self.segments < 1:
            raise ValueError(
                f"Shooting(segments={self.segments}): the number of shooting segments must be at "
                "least 1 (1 is single shooting)."
            )
        if is_concrete(self.continuity_weight) and not np.all(np.asarray(self.continuity_weight) > 0):
            raise ValueError(
                f"Shooting(continuity_weight={self.continuity_weight}): the weight of the continuity "
                "residuals must be positive."
            )
        if self.states is not None and len(self.states) != 2:
            raise ValueError(
                "Shooting(states=...) must be a pair (q, qd) of arrays of shape (E, S, n): "
                f"got {len(self.states)} items."
            )


# ----------------------------------------------------------------------------- data
class Experiment(eqx.Module):
    """One observed run: save times ``ts`` (T,), ``observations`` (T, k), initial state.

    ``q0``, ``qd0`` are the known initial state, or the starting guess when the initial state is
    estimated. NaN entries of ``observations`` are missing data and are masked out. Several
    experiments of equal shapes are passed as a list (stacked and ``vmap``-ed internally).
    """

    ts: SaveTimes
    observations: Float[ArrayLike, "times k"]
    q0: Coordinates
    qd0: Velocities


def _observe_coordinates(q, qd):
    return q


def _stack(experiments) -> Any:
    """The experiments stacked: an :class:`Experiment` of NumPy arrays with a leading axis E
    (``ts`` (E, T), ``observations`` (E, T, k), ``q0``, ``qd0`` (E, n)), not the ``ArrayLike``
    fields a user's Experiment declares."""
    if isinstance(experiments, Experiment):
        experiments = [experiments]
    experiments = list(experiments)
    if not experiments:
        raise ValueError("fit needs at least one Experiment.")
    for index, e in enumerate(experiments):
        if jnp.shape(e.q0) != jnp.shape(e.qd0) or jnp.ndim(e.q0) != 1:
            raise ValueError(
                f"Experiment {index}: q0 and qd0 must be 1-D of equal length (one entry per "
                f"coordinate); got q0 of shape {jnp.shape(e.q0)} and qd0 of shape {jnp.shape(e.qd0)}."
            )
        if jnp.shape(e.q0) != jnp.shape(experiments[0].q0):
            raise ValueError(
                f"Experiment {index}: q0 has {jnp.shape(e.q0)[0]} entries, but experiment 0's q0 "
                f"has {jnp.shape(experiments[0].q0)[0]} (one per coordinate of the system)."
            )
    shapes = {(jnp.shape(e.ts), jnp.shape(e.observations), jnp.shape(e.q0)) for e in experiments}
    if len(shapes) != 1:
        raise ValueError(
            "All experiments must have the same shapes (ts, observations, q0) to be batched with "
            f"vmap; got {sorted(shapes)}. Pad shorter ones with NaN observations."
        )
    for index, e in enumerate(experiments):
        ts = np.asarray(e.ts)
        bad_ts = np.flatnonzero(~np.isfinite(ts))
        if bad_ts.size:
            raise ValueError(
                f"Experiment {index}: save time ts[{bad_ts[0]}] = {ts[bad_ts[0]]} is not finite; "
                "save times must be finite numbers."
            )
        if ts.ndim != 1 or not np.all(np.diff(ts) > 0):
            raise ValueError("Each experiment's ts must be a strictly increasing 1-D array.")
        if not is_concrete((e.ts, e.observations, e.q0, e.qd0)):
            continue
        if np.ndim(e.observations) != 2 or np.shape(e.observations)[0] != ts.shape[0]:
            raise ValueError(
                f"observations must have shape (T, k) with T = len(ts) = {ts.shape[0]}; got "
                f"{np.shape(e.observations)}."
            )
        observations = np.asarray(e.observations)
        infinite = np.argwhere(np.isinf(observations))
        if infinite.size:
            i, k = infinite[0]
            raise ValueError(
                f"Experiment {index}: observations[{i}, {k}] (time index {i}, t = {ts[i]}) is "
                f"{observations[i, k]}. Infinite observations are not data; mark missing values "
                "with NaN (they are masked out)."
            )
        for name, value in (("q0", e.q0), ("qd0", e.qd0)):
            value = np.atleast_1d(np.asarray(value))
            bad = np.flatnonzero(~np.isfinite(value))
            if bad.size:
                raise ValueError(
                    f"Experiment {index}: {name}[{bad[0]}] = {value[bad[0]]} is not finite; the "
                    "initial state (or its starting guess) must be finite."
                )
    # Stacked on the host (NumPy, JAX's default float type): the fit's bookkeeping compiles no
    # small device programs; the arrays go to the device as inputs of the compiled programs.
    dtype = jax.dtypes.canonicalize_dtype(float)
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x, dtype) for x in xs]), *experiments)


class FitResult(eqx.Module):
    """Outcome of :func:`fit`.

    ``params``: fitted parameters (physical values, same structure as the initial guess).
    ``standard_errors``: same structure; ``covariance``: (p, p) over ``jax.flatten_util.ravel_pytree``
    order of ``params``. ``initial_states``: fitted ``(q0, qd0)`` per experiment when estimated.
    ``loss_history``: ``ℓ`` after each optimizer step (index 0 is the starting point).
    ``segment_states``: ``(q, qd)`` of shape (E, S, n), the state each shooting segment starts from.

    What the fit can vouch for (all computed at the optimum, see :func:`fit`):

    - ``standard_errors``: ``inf`` for a parameter the data cannot determine (it has a
      component along a flat direction of the residuals) or that does not affect them.
      ``covariance``: such a parameter has ``inf`` on the diagonal and NaN elsewhere in its
      row and column. ``correlation``: ``Cov_ij / √(Cov_ii Cov_jj)``, NaN rows and columns
      for those parameters.
    - ``undetermined``, ``insensitive``: the names of those parameters (``"k[1]"`` for an
      entry of an array parameter; estimated initial states as ``"q0[0] of experiment 0"``).
    - ``at_bound``: parameters that end within ``1e-6 (upper − lower)`` of a :class:`Bounded`
      transform's bound.
    - ``residual_std``: the standard deviation of the residuals, ``√(Σ r²/(N − p))`` in the
      units of the observations. ``reduced_chi2``: ``Σ (r/σ)²/(N − p)`` when ``noise_std`` is
      given (else None); about ``1 ± √(2/(N − p))`` for a good fit.
    - ``warnings``: the texts of the :class:`FitWarning` s the fit issued.
    - ``initial_state_errors``: standard errors of the estimated initial states (same
      structure as ``initial_states``), None when they are not estimated.
    - ``converged``: the optimizer's stopping criterion was met; it says nothing about the
      items above (a fit can converge to a local minimum, or to one point of a flat valley).
    """

    params: dict[str, Array]
    standard_errors: dict[str, Array]
    covariance: Float[Array, "p p"]
    residual_std: Scalar
    loss_history: Float[np.ndarray, " steps"]
    initial_states: tuple[Float[Array, "experiments n"], Float[Array, "experiments n"]]
    num_steps: int
    converged: bool
    segment_states: tuple[SegmentStates, SegmentStates] | None = None
    correlation: Float[Array, "p p"] | None = None
    reduced_chi2: float | None = None
    undetermined: tuple[str, ...] = ()
    insensitive: tuple[str, ...] = ()
    at_bound: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    initial_state_errors: tuple[Float[Array, "experiments n"], Float[Array, "experiments n"]] | None = None
    start_losses: Float[np.ndarray, " starts"] | None = None
    start_params: dict[str, Array] | None = None


class MultiStart(eqx.Module):
    """Several starting points for :func:`fit`: pass ``params=jl.MultiStart({"g": [5.0, 10.0,
    20.0], "l": [0.5, 1.0, 2.0]})``. Every leaf has a leading axis of length K (the number of
    starts; a vector parameter of length n is given as (K, n)). The fits run one after the other
    (they share the compiled programs: only the first compiles); the result is the fit with the
    lowest final loss, with every start's final loss and parameters in
    :attr:`FitResult.start_losses` / :attr:`FitResult.start_params`. A start whose fit fails
    (diverges or its simulation fails) gets loss ``inf``; only the best fit's warnings are issued.
    """

    starts: dict[str, Float[ArrayLike, " starts *shape"]]

    def __check_init__(self):
        sizes = {k: np.shape(v)[0] if np.ndim(v) else None for k, v in self.starts.items()}
        if not sizes or None in sizes.values() or len(set(sizes.values())) != 1:
            raise ValueError(
                "MultiStart needs every parameter with the same leading axis (one entry per start); "
                f"got leading sizes {sizes}."
            )


class FitWarning(UserWarning):
    """What :func:`fit` warns about: parameters the data cannot determine or that do not affect
    the residuals, a parameter ending at a bound, a fit far worse than the noise. Filter it with
    ``warnings.simplefilter("ignore", jl.FitWarning)``; the same texts are in
    :attr:`FitResult.warnings`."""


# ----------------------------------------------------------------------------- model
class _ParamSpec(eqx.Module):
    """Static description of the parameter dict, so repeated fits reuse compiled code."""

    keys: tuple = eqx.field(static=True)
    shapes: tuple = eqx.field(static=True)

    def ravel(self, params):
        return jnp.concatenate([jnp.ravel(params[k]) for k in self.keys])

    def unravel(self, flat):
        out, i = {}, 0
        for k, shape in zip(self.keys, self.shapes):
            size = int(np.prod(shape))
            out[k] = flat[i : i + size].reshape(shape)
            i += size
        return out


class _Model(eqx.Module):
    """Maps the free variables to residuals; holds everything static about the fit.

    Free variables: ``{"params": flat unconstrained parameters}`` plus, when the initial state is
    estimated, ``"states"`` (all segment states), or with multiple shooting alone ``"later"``
    (the states of segments 1..S−1; segment 0 starts from the known initial state).
    """

    system: Any
    observe: Any
    transforms: Any
    spec: _ParamSpec
    segments: int = eqx.field(static=True)
    estimate_initial_state: bool = eqx.field(static=True)
    # The options of the simulation, passed to jl.simulate. Module fields (not static): under
    # the fit's filter_jit their Python numbers are part of the cache key, so a second fit with
    # equal options reuses the compiled programs, and array-valued options are traced.
    solver: diffrax.AbstractSolver
    stepsize_controller: diffrax.AbstractStepSizeController
    max_steps: int = eqx.field(static=True)
    dt0: Any = None
    projection: Any = None
    baumgarte: Any = None
    periodic: tuple = eqx.field(static=True, default=())
    # Partial estimation: the indices of the estimated entries of (q0, qd0); None = all.
    initial_mask: tuple[tuple[int, ...], tuple[int, ...]] | None = eqx.field(static=True, default=None)

    def simulate(self, q0, qd0, ts, args, **kwargs):
        """:func:`~jaxlag.simulate` of the system with the fit's simulation options."""
        return simulate(
            self.system,
            q0,
            qd0,
            ts,
            args=args,
            solver=self.solver,
            stepsize_controller=self.stepsize_controller,
            dt0=self.dt0,
            max_steps=self.max_steps,
            projection=self.projection,
            baumgarte=self.baumgarte,
            **kwargs,
        )

    def physical(self, flat):
        params = self.spec.unravel(flat)
        return {k: self.transforms.get(k, Identity()).to_physical(v) for k, v in params.items()}

    def unconstrained(self, physical):
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

    def observations_of(self, params, data, states, adjoint, health=False):
        """The observations of every segment, their end states, and (``health=True``) what the
        host must check afterwards instead of checks compiled into the program: the simulation
        failure records and the residual of the initial-state projection, shape (E, S) each.
        The save times were checked on the host (``fit`` checks its data once)."""
        args = {**data["fixed"], **params}

        def one_segment(ts, q0, qd0):
            kwargs = {}
            residual = jnp.zeros((), q0.dtype)
            if self.system.is_constrained:
                if health:
                    q0, qd0, residual, _ = projection_with_residuals(self.system, q0, qd0, ts[0], args)
                else:
                    q0, qd0 = consistent_initial_state(self.system, q0, qd0, ts[0], args)
            if health:  # projected states are on the manifold: the failure record covers the rest
                kwargs.update(throw=False, checks=Checks(initial_state=False, times=False))
            traj = self.simulate(q0, qd0, ts, args, adjoint=adjoint, **kwargs)
            y = jax.vmap(lambda q, qd, t: self.observe(q, qd, t=t, args=args))(traj.q, traj.qd, ts)
            return y, traj.q[-1], traj.qd[-1], (traj.failure, residual)

        # states: (E, S, n) each; ts_seg: (E, S, m + 1)
        if data["ts_seg"].shape[:2] == (1, 1):
            # One experiment, one segment: no batching transform of the solver (its fixpoints
            # over diffrax's loops are most of the tracing time of the least-squares program).
            out = one_segment(data["ts_seg"][0, 0], states[0][0, 0], states[1][0, 0])
            y, q_end, qd_end, checks = jax.tree.map(lambda x: jnp.asarray(x)[None, None], out)
        else:
            y, q_end, qd_end, checks = jax.vmap(jax.vmap(one_segment))(data["ts_seg"], states[0], states[1])
        return (y, q_end, qd_end, checks) if health else (y, q_end, qd_end)

    @overload
    def residuals(self, free, data, fixed_states, adjoint, health: Literal[False] = False) -> jax.Array: ...
    @overload
    def residuals(self, free, data, fixed_states, adjoint, health: Literal[True]) -> tuple[Any, Any]: ...
    def residuals(self, free, data, fixed_states, adjoint, health: bool = False) -> Any:
        """The weighted residuals; with ``health=True`` also the checks of
        :meth:`observations_of` (the host raises with :func:`_raise_for_health`)."""
        params = self.physical(free["params"])
        states = self.states(free, fixed_states)
        y, q_end, qd_end, *checks = self.observations_of(params, data, states, adjoint, health)
        # Stitch segments back to the save grid: drop each later segment's first (shared) point.
        e = y.shape[0]
        rest = y[:, 1:, 1:].reshape(e, -1, y.shape[-1])
        y = jnp.concatenate([y[:, 0], rest], axis=1)
        observed = data["observations"]
        mask = jnp.isfinite(observed)
        r = jnp.where(mask, (y - jnp.where(mask, observed, 0.0)) / data["noise"], 0.0)
        pieces = [r.ravel()]
        if self.segments > 1:
            w = data["continuity_weight"]
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


def _residuals_and_jacobian(model, free, data, fixed_states):
    """``(r, J, y)``: the residuals at the free variables ``free``, their Jacobian with respect to
    the raveled free variables ``y`` (``jax.flatten_util.ravel_pytree`` order) and ``y``.

    Forward mode, one tangent per free scalar under ``vmap`` (the primal solve is not batched,
    so it runs once). This is the one large program of a least-squares fit: the optimizer's own
    step only sees the linear model built from it (:func:`_linear_model`). Its checks (a failed
    simulation, an initial state that cannot be projected) are returned and raised here, on the
    host: the program has no host callback, so JAX's persistent cache stores it.
    """
    r, jacobian, flat, checks = _linearize(model, free, data, fixed_states)
    _raise_for_health(model, checks, free["params"], data)
    return r, jacobian, flat


@compilation.filter_jit
def _linearize(model, free, data, fixed_states):
    flat, unravel = ravel_pytree(free)

    def residuals(y):
        return model.residuals(unravel(y), data, fixed_states, diffrax.ForwardMode(), health=True)

    def push(direction):
        return jax.jvp(residuals, (flat,), (direction,), has_aux=True)

    if flat.shape[0] == 1:  # one free variable: a plain jvp, no size-1 batch of the solver
        r, column, checks = push(jnp.ones_like(flat))
        return r, column[:, None], flat, checks
    r, columns, checks = jax.vmap(push, out_axes=(None, 0, None))(jnp.eye(flat.shape[0], dtype=flat.dtype))
    return r, columns.T, flat, checks


def _raise_for_health(model, checks, flat_params, data) -> None:
    """Raise what the checks of :meth:`_Model.observations_of` found (host side): an initial
    state the projection could not bring onto the constraint manifold (``ValueError``, as
    :func:`~jaxlag.consistent_initial_state`), or a failed simulation (``SimulationError``, with
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
    failed = np.argwhere(np.asarray(failure.code) != failures.NONE)
    if failed.size:
        index = tuple(failed[0])
        params = model.physical(flat_params)  # only now: eager operations compile
        args = jax.device_get({**data["fixed"], **params})
        text = failures.describe(failures.member(failure, index), model.system, args)
        raise failures.SimulationError(
            f"jl.fit, {where(index)}, at parameters "
            + ", ".join(f"{k}={np.asarray(v)}" for k, v in params.items())
            + ": "
            + text
        )


def _linear_model(free, linearization):
    """``r + J (y − y₀)``: the residuals linearized at ``y₀`` (``linearization = (r, J, y₀)``).

    optimistix' Gauss–Newton/Levenberg–Marquardt step evaluates the residual function only at
    its trial point ``state.y_eval`` and linearizes it there; given the linearization at that
    point this model has the same value (``r``) and the same Jacobian (``J``), so the step is the
    one the solver takes on the simulation itself, without tracing the simulation into it.
    """
    r, jacobian, anchor = linearization
    return r + jacobian @ (ravel_pytree(free)[0] - anchor), None


@compilation.filter_jit
def _ls_init(solver, free, linearization):
    f_struct, aux_struct = jax.eval_shape(_linear_model, free, linearization)
    return solver.init(_linear_model, free, linearization, {}, f_struct, aux_struct, frozenset())


@compilation.filter_jit
def _ls_step(solver, free, state, linearization):
    """One optimistix step at ``state.y_eval`` (where ``linearization`` was taken); also the loss
    at the returned point: optimistix keeps the residuals of the last accepted point (the
    returned one) in ``state.f_info`` (after the first step, which only evaluates, the loss at
    the start)."""
    free, state, _ = solver.step(_linear_model, free, linearization, {}, state, frozenset())
    done, _ = solver.terminate(_linear_model, free, linearization, {}, state, frozenset())
    # At the optimum the actual reduction is rounding noise and trial steps can be rejected
    # (the trust region then shrinks the step 4x per step, up to ~16 more steps): a rejected
    # trial whose step is already within the solver's y tolerance ends the fit, as further
    # steps could not move the parameters by more than that tolerance.
    y = ravel_pytree(free)[0]
    trial = ravel_pytree(state.y_eval)[0] - y
    within = solver.norm(jnp.abs(trial) / (solver.atol + solver.rtol * jnp.abs(y))) < 1
    done = done | (within & (state.num_steps_since_acceptance > 0))
    loss = 0.5 * jnp.sum(state.f_info.residual**2)
    return free, state, done, loss


@compilation.filter_jit
def _value_and_grad(model, free, data, fixed_states):
    # The default adjoint: forward sensitivities for up to 10 free scalars, else checkpointed.
    adjoint = ForwardSensitivities()
    return jax.value_and_grad(lambda f: 0.5 * jnp.sum(model.residuals(f, data, fixed_states, adjoint) ** 2))(
        free
    )


@compilation.filter_jit
def _optax_update(optimizer, free, opt_state, grads):

    updates, opt_state = optimizer.update(grads, opt_state, free)
    return optax.apply_updates(free, updates), opt_state


@compilation.filter_jit
def _free_variables_jacobian(model, x, free_template):
    """``∂y/∂x``: the raveled free variables ``y`` with respect to ``x`` = (physical parameters
    in ``spec`` order, the other free variables raveled): the chain rule of the
    reparameterizations, for the Jacobian in physical parameters."""
    p = len(model.spec.ravel(model.physical(free_template["params"])))
    rest_template = {k: v for k, v in free_template.items() if k != "params"}
    _, unravel_rest = ravel_pytree(rest_template)

    def free_of(x_):
        free = {"params": model.unconstrained(model.spec.unravel(x_[:p])), **unravel_rest(x_[p:])}
        return ravel_pytree(free)[0]

    return jax.jacfwd(free_of)(x)


@compilation.filter_jit
def _guess_states(model, ts, q0, qd0, args, starts):
    guess = jax.vmap(lambda t, a, b: model.simulate(a, b, t, args))(ts, q0, qd0)
    return guess.q[:, starts], guess.qd[:, starts]


def _segment_grid(ts, segments):
    t = ts.shape[-1]
    if (t - 1) % segments:
        raise ValueError(
            f"Shooting(segments={segments}): the number of segments must divide len(ts) − 1 = "
            f"{t - 1} (segments share their boundary save times)."
        )
    m = (t - 1) // segments
    index = np.arange(segments)[:, None] * m + np.arange(m + 1)[None, :]
    return np.asarray(ts)[:, index], index[:, 0]


def fit(
    system: System,
    params: dict[str, ArrayLike] | MultiStart,
    experiments: Experiment | Sequence[Experiment],
    *,
    observe: Callable | None = None,
    args: dict | None = None,
    transforms: dict[str, Positive | Bounded] | None = None,
    optimizer: optx.AbstractLeastSquaresSolver | optax.GradientTransformation = optx.LevenbergMarquardt(
        rtol=1e-10, atol=1e-10
    ),
    max_steps: int = 100,
    noise_std: float | None = None,
    estimate_initial_state: bool | tuple[Bool[ArrayLike, " n"], Bool[ArrayLike, " n"]] = False,
    shooting: Shooting = Shooting(),
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stepsize_controller: diffrax.AbstractStepSizeController = diffrax.PIDController(rtol=1e-10, atol=1e-10),
    dt0: float | None = None,
    max_solver_steps: int = 16384,
    projection: Projection | None = Projection(),
    baumgarte: Baumgarte | None = None,
    progress: bool = False,
) -> FitResult:
    """Fit ``params`` of ``system`` to ``experiments`` by least squares.

    **Arguments:**

    - ``system``: the :class:`~jaxlag.System` (constraints, dissipation and forces included).
    - ``params``: dict of free parameters with their starting values, or a :class:`MultiStart`
      of several starting points (the best fit is returned).
    - ``experiments``: an :class:`Experiment` or a list of them (equal shapes; batched by vmap).
    - ``observe``: ``observe(q, qd, [t], [args]) -> (k,)``, what was measured (default: ``q``).
      It matters: for a pendulum ``θ(t)`` depends only on ``g/l``, while the bob's Cartesian
      position ``l (sin θ, −cos θ)`` identifies ``g`` and ``l`` separately.
    - ``args``: fixed parameters, merged with ``params`` into the ``args`` the system sees.
    - ``transforms``: per-parameter :class:`Positive` / :class:`Bounded` reparameterizations.
    - ``optimizer``: an optimistix least-squares solver of the Gauss–Newton family (a subclass
      of ``optx.AbstractGaussNewton``: ``optx.LevenbergMarquardt`` (default, ``rtol = atol =
      1e-10``), ``optx.GaussNewton``, ``optx.Dogleg``, ``optx.IndirectLevenbergMarquardt``),
      whose ``rtol``/``atol`` are the fit's tolerances; or an ``optax.GradientTransformation``
      (gradient descent on the loss). Other optimistix solvers are refused (``TypeError``): the
      fit steps the solver on a linearization of the residuals, which needs its Gauss–Newton
      state.
    - ``max_steps``: the most optimizer steps.
    - ``noise_std``: known observation noise σ; if None it is estimated from the residuals.
    - ``estimate_initial_state``: also fit each experiment's ``(q0, qd0)`` (``True``), or only
      some entries: a pair of boolean masks ``(q_mask, qd_mask)`` of shape (n,) each, True =
      estimated (the same entries in every experiment); the others stay at the experiment's
      ``q0``/``qd0``, which are then known values. E.g. ``(jnp.array([True]),
      jnp.array([False]))``: θ0 free, θ̇0 known.
    - ``shooting``: a :class:`Shooting` (segments, continuity weight, starting guesses of the
      segment states, periodic coordinates); the default ``Shooting()`` is single shooting.
    - ``solver``, ``stepsize_controller``, ``dt0``, ``projection``, ``baumgarte``: passed to
      :func:`~jaxlag.simulate`; ``max_solver_steps`` is its ``max_steps`` (the most integrator
      steps of one simulation).
    - ``progress``: show a tqdm progress bar (``pip install tqdm``).

    Returns a :class:`FitResult`.
    """
    if isinstance(params, MultiStart):
        options = dict(
            observe=observe, args=args, transforms=transforms, optimizer=optimizer,
            max_steps=max_steps, noise_std=noise_std, estimate_initial_state=estimate_initial_state,
            shooting=shooting, solver=solver, stepsize_controller=stepsize_controller, dt0=dt0,
            max_solver_steps=max_solver_steps, projection=projection, baumgarte=baumgarte,
            progress=progress,
        )  # fmt: skip
        return _multi_start(system, params, experiments, options)
    batch = _stack(experiments)
    transforms = dict(transforms or {})
    unknown = set(transforms) - set(params)
    if unknown:
        raise ValueError(f"transforms name parameters that are not being fitted: {sorted(unknown)}.")
    observe = wrap_state_function(observe or _observe_coordinates, "observation function")
    least_squares = _check_optimizer(optimizer)
    if not isinstance(shooting, Shooting):
        raise TypeError(
            f"shooting must be a jl.Shooting, e.g. shooting=jl.Shooting(segments=4); got {shooting!r}."
        )
    real = jax.dtypes.canonicalize_dtype(float)  # on the host: no eager device conversions
    fixed = {k: np.asarray(v, real) if isinstance(v, (int, float)) else v for k, v in (args or {}).items()}
    params = {k: np.asarray(v, real) for k, v in params.items()}
    _check_starts(params, transforms)

    # Shapes of the observation function against the data.
    q_probe = batch.q0[0]
    out = jax.eval_shape(
        lambda q, qd: observe(q, qd, t=batch.ts[0, 0], args={**fixed, **params}), q_probe, batch.qd0[0]
    )
    if out.shape != batch.observations.shape[2:]:
        raise ValueError(
            f"The observation function returns shape {out.shape} per time, but the observations "
            f"have shape {batch.observations.shape[2:]} per time."
        )
    if not np.any(np.isfinite(np.asarray(batch.observations))):
        raise ValueError("All observations are NaN: nothing to fit.")

    initial_mask = _initial_mask(estimate_initial_state, batch.q0.shape[-1])
    spec = _ParamSpec(tuple(params), tuple(jnp.shape(v) for v in params.values()))
    model = _Model(
        system,
        observe,
        transforms,
        spec,
        segments=int(shooting.segments),
        estimate_initial_state=initial_mask is not None or estimate_initial_state is True,
        initial_mask=initial_mask,
        solver=solver,
        stepsize_controller=stepsize_controller,
        max_steps=int(max_solver_steps),
        dt0=dt0,
        projection=projection,
        baumgarte=baumgarte,
        periodic=shooting.periodic_coordinates,
    )
    segments = model.segments
    ts_seg, starts = _segment_grid(batch.ts, segments)
    num_experiments = batch.ts.shape[0]
    segment_states = shooting.states
    if segment_states is None:
        if segments > 1:
            segment_states = _guess_states(model, batch.ts, batch.q0, batch.qd0, {**fixed, **params}, starts)
        else:
            segment_states = (batch.q0[:, None], batch.qd0[:, None])
    segment_states = tuple(np.asarray(s, batch.q0.dtype) for s in segment_states)
    expected = (num_experiments, segments, batch.q0.shape[-1])
    if segment_states[0].shape != expected or segment_states[1].shape != expected:
        raise ValueError(
            f"Shooting(states=(q, qd)) must have shape {expected} each (experiments, segments, "
            f"coordinates); got {segment_states[0].shape} and {segment_states[1].shape}."
        )

    data = {
        "fixed": fixed,
        "observations": batch.observations,
        "noise": 1.0 if noise_std is None else float(noise_std),
        "ts_seg": ts_seg,
        "continuity_weight": float(shooting.continuity_weight),
    }
    free_states, fixed_states = model.split(segment_states)
    free = {"params": _unconstrained(model, params), **free_states}

    bar = _progress_bar(max_steps, progress)
    history, converged, steps = [], False, 0
    linearization = None
    if least_squares:
        # Each step: the simulation's residuals and Jacobian at the trial point (one compiled
        # program), then the optimizer's step on that linearization (a small one).
        linearization = _residuals_and_jacobian(model, free, data, fixed_states)
        state = _ls_init(optimizer, free, linearization)
        if max_steps < 1:
            history.append(float(0.5 * np.sum(np.asarray(linearization[0]) ** 2)))
        for steps in range(1, max_steps + 1):
            if steps > 1:
                linearization = _residuals_and_jacobian(model, state.y_eval, data, fixed_states)
            free, state, done, loss = _ls_step(optimizer, free, state, linearization)
            loss, done = jax.device_get((loss, done))
            if steps == 1:  # the first step evaluates the starting point and stays there
                history.append(float(loss))
            history.append(float(loss))
            _tick(bar, history[-1])
            if bool(done):
                converged = True
                break
    else:
        opt_state = cast(optax.GradientTransformation, optimizer).init(free)  # _check_optimizer
        for steps in range(1, max_steps + 1):
            value, grads = _value_and_grad(model, free, data, fixed_states)
            history.append(float(value))
            free, opt_state = _optax_update(optimizer, free, opt_state, grads)
            _tick(bar, history[-1])
        history.append(float(_value_and_grad(model, free, data, fixed_states)[0]))
        converged = True
    if bar is not None:
        bar.close()
    if not np.isfinite(history[-1]):
        raise FloatingPointError(
            "The fit diverged (non-finite loss): start closer, bound the "
            "parameters with `transforms`, or lower the learning rate."
        )

    flat = np.concatenate([np.ravel(np.asarray(leaf)) for leaf in jax.tree.leaves(free)])
    if linearization is not None and np.array_equal(flat, np.asarray(linearization[2])):
        r, jac_free, _ = linearization  # the last step was taken at (and accepted) this point
    else:
        r, jac_free, _ = _residuals_and_jacobian(model, free, data, fixed_states)
    observed = int(np.sum(np.isfinite(np.asarray(batch.observations))))
    fitted, jac, x, states = jax.device_get(_summary(model, free, fixed_states, jac_free))
    r, jac, x = np.asarray(r), np.asarray(jac), np.asarray(x)
    dof = max(observed - flat.size, 1)
    chi2 = float(np.sum(r**2))
    if noise_std is None:
        sigma2 = chi2 / dof
        residual_std = np.sqrt(sigma2)
        reduced_chi2 = None
    else:
        sigma2 = 1.0
        residual_std = float(noise_std) * np.sqrt(chi2 / dof)
        reduced_chi2 = chi2 / dof
    names = _column_names(spec, model, num_experiments, batch.q0.shape[-1])
    covariance, errors, insensitive, null = _rank_revealing(jac, x, sigma2, names)
    p = len(spec.ravel(fitted))
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = covariance / np.sqrt(np.outer(np.diag(covariance), np.diag(covariance)))
    correlation[~np.isfinite(errors), :] = np.nan
    correlation[:, ~np.isfinite(errors)] = np.nan
    messages = [f"{names[j]} does not affect the residuals" for j in insensitive]
    messages += _describe_null(null, x, names)
    undetermined = tuple(names[j] for j in np.flatnonzero(~np.isfinite(errors)) if j not in insensitive)
    at_bound = []
    for name, transform in transforms.items():
        if isinstance(transform, Bounded):
            value = np.ravel(np.asarray(fitted[name]))
            width = transform.upper - transform.lower
            near = np.minimum(value - transform.lower, transform.upper - value) <= 1e-6 * width
            for i in np.flatnonzero(near):
                where = name if np.ndim(fitted[name]) == 0 else f"{name}[{i}]"
                at_bound.append(where)
                messages.append(
                    f"{where} = {value[i]:.6g} ends at a bound of Bounded({transform.lower}, "
                    f"{transform.upper}) (within 1e-6 of the interval's width): the data pull it "
                    "outside the interval; widen the bounds or check the model"
                )
    if noise_std is not None and reduced_chi2 is not None and reduced_chi2 > 1 + 5 * np.sqrt(2 / dof):
        messages.append(
            f"the fit ends with reduced χ² = {reduced_chi2:.3g} (residual std {residual_std:.3g} for "
            f"noise_std {float(noise_std):.3g}), beyond 1 + 5·√(2/{dof}) = "
            f"{1 + 5 * np.sqrt(2 / dof):.3g}: the fit ends at a local minimum or the model does not "
            "describe the data; try another start"
        )
    for message in messages:
        warnings.warn(f"jl.fit: {message}.", FitWarning, stacklevel=2)
    standard_errors = spec.unravel(jnp.asarray(errors[:p]))
    initial_state_errors = None
    if model.estimate_initial_state and model.initial_mask is not None:
        # Known entries: standard error 0; estimated ones in ravel order (q entries, then qd).
        shape = np.shape(states[0][:, 0])
        q_se, qd_se, start = np.zeros(shape), np.zeros(shape), p
        for target, indices in zip((q_se, qd_se), model.initial_mask):
            size = shape[0] * len(indices)
            target[:, list(indices)] = errors[start : start + size].reshape(shape[0], len(indices))
            start += size
        initial_state_errors = (jnp.asarray(q_se), jnp.asarray(qd_se))
    elif model.estimate_initial_state:
        state_errors = errors[p:].reshape((2, *np.shape(states[0])))
        initial_state_errors = (jnp.asarray(state_errors[0][:, 0]), jnp.asarray(state_errors[1][:, 0]))
    initial = (states[0][:, 0], states[1][:, 0])
    return FitResult(
        fitted,
        standard_errors,
        jnp.asarray(covariance[:p, :p]),
        jnp.asarray(residual_std),
        np.asarray(history),
        initial,
        steps,
        converged,
        states,
        correlation=jnp.asarray(correlation[:p, :p]),
        reduced_chi2=reduced_chi2,
        undetermined=undetermined,
        insensitive=tuple(names[j] for j in insensitive),
        at_bound=tuple(at_bound),
        warnings=tuple(messages),
        initial_state_errors=initial_state_errors,
    )


def _multi_start(system, starts: MultiStart, experiments, options) -> FitResult:
    """:func:`fit` from each start of ``starts`` in turn; the best result, with all of them."""
    count = next(iter(np.shape(v)[0] for v in starts.starts.values()))
    results, losses, error = [], [], None
    for k in range(count):
        start = {name: np.asarray(value)[k] for name, value in starts.starts.items()}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FitWarning)
            try:
                result = fit(system, start, experiments, **options)
            except (FloatingPointError, failures.SimulationError) as caught:
                result, error = None, caught
        results.append(result)
        losses.append(np.inf if result is None else float(result.loss_history[-1]))
    best = int(np.argmin(losses))
    result = results[best]
    if result is None:
        raise ValueError(f"MultiStart: every one of the {count} fits failed; the last: {error}") from error
    for message in result.warnings:
        warnings.warn(f"jl.fit: {message}.", FitWarning, stacklevel=3)
    names = tuple(result.params)
    start_params = {
        name: jnp.stack(
            [
                jnp.asarray(r.params[name]) if r is not None else jnp.full_like(result.params[name], jnp.nan)
                for r in results
            ]
        )
        for name in names
    }
    return eqx.tree_at(
        lambda r: (r.start_losses, r.start_params),
        result,
        (np.asarray(losses), start_params),
        is_leaf=lambda x: x is None,
    )


def _initial_mask(estimate, n):
    """The indices ``(q, qd)`` of the estimated initial-state entries of a mask pair, None for a
    plain ``True``/``False``; a ``ValueError`` naming what is wrong with a malformed mask."""
    if isinstance(estimate, (bool, np.bool_)):
        return None
    if not (isinstance(estimate, (tuple, list)) and len(estimate) == 2):
        raise ValueError(
            "estimate_initial_state must be True, False or a pair of boolean masks (q_mask, "
            f"qd_mask) of shape ({n},) each; got {estimate!r}."
        )
    indices = []
    for name, mask in zip(("q_mask", "qd_mask"), estimate):
        mask = np.asarray(mask)
        if mask.dtype != np.bool_ or mask.shape != (n,):
            raise ValueError(
                f"estimate_initial_state: {name} must be a boolean array of shape ({n},) (one entry "
                f"per coordinate, True = estimated); got dtype {mask.dtype} and shape {mask.shape}."
            )
        indices.append(tuple(int(i) for i in np.flatnonzero(mask)))
    return (indices[0], indices[1])


def _check_starts(params, transforms) -> None:
    """A ``ValueError`` naming a starting value that is not finite or lies outside its
    transform's open domain (``Positive``: > 0; ``Bounded(a, b)``: strictly inside (a, b))."""
    for name, value in params.items():
        flat = np.ravel(value)
        transform = transforms.get(name, Identity())
        if isinstance(transform, Positive):
            inside, domain = flat > 0, "(0, inf) of jl.Positive()"
        elif isinstance(transform, Bounded):
            inside = (flat > transform.lower) & (flat < transform.upper)
            domain = f"the open interval ({transform.lower}, {transform.upper}) of jl.Bounded"
        else:
            inside, domain = np.isfinite(flat), "finite numbers"
        bad = np.flatnonzero(~(inside & np.isfinite(flat)))
        if bad.size:
            where = name if np.ndim(value) == 0 else f"{name}[{bad[0]}]"
            raise ValueError(
                f"The starting value {where} = {flat[bad[0]]} is outside the domain {domain}; "
                "start strictly inside it."
            )


def _check_optimizer(optimizer) -> bool:
    """Whether ``optimizer`` is an optimistix least-squares solver that :func:`fit` can step
    (``True``) or an optax optimizer (``False``); a ``TypeError`` for anything else."""
    if isinstance(optimizer, optx.AbstractGaussNewton):
        return True
    if isinstance(optimizer, optax.GradientTransformation):
        return False
    supported = (
        "optx.LevenbergMarquardt, optx.GaussNewton, optx.Dogleg or optx.IndirectLevenbergMarquardt "
        "(subclasses of optx.AbstractGaussNewton)"
    )
    if isinstance(optimizer, str):
        solver = {"levenberg_marquardt": "LevenbergMarquardt", "gauss_newton": "GaussNewton"}.get(optimizer)
        hint = (
            f" Pass optimizer=optx.{solver}(rtol=1e-10, atol=1e-10) (import optimistix as optx)."
            if solver
            else ""
        )
        raise TypeError(
            f"optimizer must be a solver object, not the string {optimizer!r}: one of {supported}, "
            f"or an optax.GradientTransformation.{hint}"
        )
    if isinstance(optimizer, optx.AbstractLeastSquaresSolver):
        raise TypeError(
            f"jl.fit steps the least-squares solver on a linearization of the residuals, which needs "
            f"a Gauss–Newton-type solver: {supported}; got {type(optimizer).__name__}."
        )
    raise TypeError(
        f"optimizer must be an optimistix least-squares solver, {supported}, or an "
        f"optax.GradientTransformation (gradient descent on the loss); got {type(optimizer).__name__}."
    )


@compilation.filter_jit
def _unconstrained(model, params):
    """The free parameters (raveled, unconstrained) of the physical ``params``."""
    return model.unconstrained(params)


@compilation.filter_jit
def _summary(model, free, fixed_states, jac_free):
    """At the optimum, in one program: the physical parameters, the Jacobian of the weighted
    residuals with respect to the physical parameters (then the free segment states), their
    values in that order, and the segment states."""
    fitted = model.physical(free["params"])
    physical = model.spec.ravel(fitted)
    free_states = ravel_pytree({k: v for k, v in free.items() if k != "params"})[0]
    x = jnp.concatenate([physical, free_states.astype(physical.dtype)])  # ravel_pytree({}): float32
    jac = jac_free @ _free_variables_jacobian(model, x, free)
    states = model.states(free, fixed_states)
    return fitted, jac, x, states


def _column_names(spec, model, num_experiments, n) -> list[str]:
    names = []
    for key, shape in zip(spec.keys, spec.shapes):
        if shape == ():
            names.append(key)
        else:
            names.extend(f"{key}[{', '.join(map(str, i))}]" for i in np.ndindex(*shape))
    if model.estimate_initial_state and model.initial_mask is not None:
        for kind, indices in zip(("q", "qd"), model.initial_mask):
            for e in range(num_experiments):
                names.extend(f"{kind}0[{i}] of experiment {e}" for i in indices)
    if model.estimate_initial_state and model.initial_mask is None:
        for kind in ("q", "qd"):
            for e in range(num_experiments):
                for seg in range(model.segments):
                    label = f"{kind}0" if seg == 0 else f"{kind} at segment {seg}"
                    names.extend(f"{label}[{i}] of experiment {e}" for i in range(n))
    if model.segments > 1 and (not model.estimate_initial_state or model.initial_mask is not None):
        for kind in ("q", "qd"):
            for e in range(num_experiments):
                for seg in range(1, model.segments):
                    names.extend(f"{kind} at segment {seg}[{i}] of experiment {e}" for i in range(n))
    return names


def _rank_revealing(jac, x, sigma2, names):
    """The covariance ``σ² (JᵀJ)⁻¹`` restricted to what the data determine, by an SVD.

    A variable whose sensitivity is negligible, ``|J_j| s_j ≤ √ε · max_k |J_k| s_k`` with
    ``s_j = max(|x_j|, 1)`` (a change of it by ``s_j`` moves the residuals by less than ``√ε``
    of what such a change of the most sensitive one does), does not affect the residuals; the
    test catches columns that are rounding noise (a mass that cancels from the motion), which
    equilibration would otherwise blow up to unit norm. The others are scaled to unit norm
    (equilibration: the threshold then does not depend on the parameters' units) and
    decomposed, ``J D⁻¹ = U S Vᵀ``; singular values ``s < √ε · s_max`` span the directions the
    data cannot determine. Not ``max(N, p) ε s_max``: the Jacobian comes from forward
    sensitivities integrated at the solver's tolerance (≈1e-10), far less accurate than ``ε``,
    so a structural degeneracy (only ``g/l`` enters) can show up well above rounding level;
    and a combination determined ``1/√ε ≈ 7e7`` times worse than the best one is no estimate.
    Every variable with a component (``> √ε``) in those directions gets an
    infinite standard error. Returns ``(covariance, standard errors, insensitive indices,
    null vectors in physical units)``.
    """
    eps = np.finfo(jac.dtype).eps
    norms = np.linalg.norm(jac, axis=0)
    relative = norms * np.maximum(np.abs(x), 1.0)  # change of r for a change of x by max(|x|, 1)
    scale = relative.max() if relative.size and relative.max() > 0 else 1.0
    insensitive = np.flatnonzero(~(relative > np.sqrt(eps) * scale))
    active = np.flatnonzero(relative > np.sqrt(eps) * scale)
    p = jac.shape[1]
    covariance = np.full((p, p), np.nan)
    errors = np.full(p, np.inf)
    null = np.zeros((0, p))
    if active.size:
        d = norms[active]
        _, sv, vt = np.linalg.svd(jac[:, active] / d, full_matrices=True)
        sv = np.concatenate([sv, np.zeros(active.size - sv.size)])
        keep = sv >= np.sqrt(eps) * sv[0]
        vk = vt[keep].T / d[:, None]  # back to physical units
        sub = sigma2 * (vk / sv[keep] ** 2) @ vk.T
        vn = vt[~keep]  # equilibrated null directions
        undetermined = np.zeros(active.size, bool)
        if vn.size:
            undetermined = np.linalg.norm(vn, axis=0) > np.sqrt(eps)
            null_phys = np.zeros((vn.shape[0], p))
            null_phys[:, active] = vn / d
            null = null_phys
        covariance[np.ix_(active, active)] = sub
        ok = active[~undetermined]
        errors[ok] = np.sqrt(np.diag(covariance)[ok])
        bad = active[undetermined]
        covariance[bad, :] = np.nan
        covariance[:, bad] = np.nan
    covariance[insensitive, :] = np.nan
    covariance[:, insensitive] = np.nan
    for j in np.flatnonzero(~np.isfinite(errors)):
        covariance[j, j] = np.inf
    return covariance, errors, insensitive, null


def _describe_null(null, x, names) -> list[str]:
    """Words for the directions the data cannot determine (rows of ``null``, physical units)."""
    if null.shape[0] == 0:
        return []
    tol = 1e-6
    if null.shape[0] > 1:
        involved = np.flatnonzero(np.linalg.norm(null, axis=0) > tol * np.abs(null).max())
        return [
            f"the data cannot determine {null.shape[0]} combinations of "
            + ", ".join(names[j] for j in involved)
            + ": they can change together without changing the residuals"
        ]
    v = null[0]
    involved = np.flatnonzero(np.abs(v) > tol * np.abs(v).max())
    if np.all(x[involved] != 0):
        u = v[involved] / x[involved]  # d log x along the flat direction
        u = u / u[np.argmax(np.abs(u))]
        if involved.size == 2 and abs(abs(u[0]) - abs(u[1])) < 1e-3:
            a, b = (names[j] for j in involved)
            if u[0] * u[1] > 0:
                return [
                    f"only {a}/{b} is determined by the data: {a} and {b} can be scaled together "
                    "without changing the residuals"
                ]
            return [
                f"only {a}·{b} is determined by the data: {a} can be scaled up and {b} down by "
                "the same factor without changing the residuals"
            ]
        terms = " + ".join(f"{c:.3g}·d log {names[j]}" for c, j in zip(u, involved))
        return [
            f"the data cannot determine the direction {terms}: "
            + ", ".join(names[j] for j in involved)
            + " can change together along it without changing the residuals"
        ]
    w = v[involved] / v[involved][np.argmax(np.abs(v[involved]))]
    terms = " + ".join(f"{c:.3g}·d{names[j]}" for c, j in zip(w, involved))
    return [f"the data cannot determine the direction {terms} (it leaves the residuals unchanged)"]


def _tick(bar, loss):
    if bar is not None:
        bar.update(1)
        bar.set_postfix(loss=loss)


def _progress_bar(total, enabled):
    if not enabled:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError("progress=True needs tqdm: pip install tqdm") from error
    return tqdm(total=total, desc="jaxlag.fit")


def least_squares_loss(
    system: System,
    params: dict[str, ArrayLike],
    experiments: Experiment | Sequence[Experiment],
    *,
    observe: Callable | None = None,
    args: dict | None = None,
    noise_std: float = 1.0,
    solver: diffrax.AbstractSolver = diffrax.Tsit5(),
    stepsize_controller: diffrax.AbstractStepSizeController = diffrax.PIDController(rtol=1e-10, atol=1e-10),
    dt0: float | None = None,
    max_solver_steps: int = 2**16,
    adjoint: diffrax.AbstractAdjoint | ForwardSensitivities = ForwardSensitivities(),
    projection: Projection | None = Projection(),
    baumgarte: Baumgarte | None = None,
) -> Scalar:
    """The fit's loss ``½ Σ r²`` at physical ``params`` (single shooting, known initial states).

    Differentiable with ``jax.grad`` (the default ``adjoint``, as in :func:`~jaxlag.simulate`)
    and ``jax.jacfwd`` (pass ``adjoint=diffrax.ForwardMode()``); useful to check gradients or to
    drive your own optimizer. ``solver``, ``stepsize_controller``, ``dt0``, ``adjoint``,
    ``projection`` and ``baumgarte`` are passed to :func:`~jaxlag.simulate`, and
    ``max_solver_steps`` as its ``max_steps``.
    """
    batch = _stack(experiments)
    observe = wrap_state_function(observe or _observe_coordinates, "observation function")
    spec = _ParamSpec(tuple(params), tuple(jnp.shape(v) for v in params.values()))
    model = _Model(
        system,
        observe,
        {},
        spec,
        segments=1,
        estimate_initial_state=False,
        solver=solver,
        stepsize_controller=stepsize_controller,
        max_steps=int(max_solver_steps),
        dt0=dt0,
        projection=projection,
        baumgarte=baumgarte,
    )
    data = {
        "fixed": dict(args or {}),
        "observations": batch.observations,
        "noise": noise_std,
        "ts_seg": batch.ts[:, None, :],
        "continuity_weight": 0.0,
    }
    if is_concrete(batch.observations) and not np.any(np.isfinite(np.asarray(batch.observations))):
        raise ValueError(
            "least_squares_loss: no observation is finite (all are NaN or inf): the loss would be "
            "0, a perfect fit of no data."
        )
    free = {"params": spec.ravel({k: jnp.asarray(v, float) for k, v in params.items()})}
    r = model.residuals(free, data, (batch.q0[:, None], batch.qd0[:, None]), adjoint)
    return 0.5 * jnp.sum(r**2)
