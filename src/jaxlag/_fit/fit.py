r"""System identification: fit parameters (and initial states) to observed trajectories.

The model of experiment ``e`` at save time ``t_i`` is ``y_e(t_i) = observe(q(t_i), q̇(t_i), t_i, args)``
where ``(q, q̇)`` comes from [`simulate`][jaxlag.simulate] with ``args = {**fixed_args, **params}``.
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
  through the simulation (the default [`ForwardSensitivities`][jaxlag.ForwardSensitivities]: forward
  sensitivities for up to 10 free scalars, else ``diffrax.RecursiveCheckpointAdjoint``).

Standard errors come from the Gauss–Newton approximation at the optimum: with the Jacobian
``J = ∂r/∂θ`` in physical parameters, ``Cov = σ̂² (JᵀJ)⁻¹``, where ``σ̂² = |r|²/(N − p)`` is
estimated from the residuals unless ``noise_std`` is given (then ``Cov = (JᵀJ)⁻¹``). The
inverse is rank-revealing (an SVD of ``J`` with its columns scaled to unit norm, singular
values below ``√ε · s_max`` dropped): a parameter along a direction the data cannot determine,
or one that does not affect the residuals, gets an infinite standard error, its name in
``FitResult.undetermined`` / ``FitResult.insensitive``, and a `FitWarning` that says
which combination is determined (``only g/l is determined by the data``). The fit also warns
when a parameter ends at a `Bounded` bound, and, with ``noise_std`` given, when the
reduced χ² exceeds ``1 + 5 √(2/(N − p))`` (five standard deviations of the χ² distribution
above its mean: a local minimum, or a model that does not describe the data).

Chaotic or long trajectories: ``shooting=Shooting(segments=S)`` splits each experiment into
``S`` segments, each starting from its own free state, and adds continuity residuals
``w (x_end(segment k) − x_start(segment k+1))`` (multiple shooting).
"""

import warnings
from collections.abc import Callable, Sequence
from typing import cast

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from jaxtyping import ArrayLike, Bool
from typing_extensions import TypedDict, Unpack

from .. import _errors as failures
from .._adjoint import ForwardSensitivities
from .._checks import Checks
from .._conventions import wrap_state_function
from .._custom_types import Scalar
from .._misc import is_concrete
from .._options import SimulateOptions
from .._stabilization import Baumgarte, Projection
from .._system import System
from .checks import (
    DEPRECATED_SIMULATION_KEYWORDS,
    FIT_CONTROLS,
    check_observations,
    check_optimizer,
    check_options,
    check_starts,
    initial_mask,
    simulation_options,
)
from .data import Data, Experiment, save_times, segment_grid, stack
from .diagnostics import gross_outliers
from .loops import least_squares_loop, optax_loop
from .model import Model, ParamSpec, Problem, guess_states, residuals_and_jacobian, unconstrained
from .options import Bounded, FitWarning, MultiStart, Positive, Shooting
from .statistics import FitResult, fit_result


def _observe_coordinates(q, qd):
    return q


class DeprecatedSimulationKeywords(TypedDict, total=False):
    """The keywords of `fit` that ``simulation=`` replaces (deprecated, removed in the next
    release)."""

    solver: diffrax.AbstractSolver
    stepsize_controller: diffrax.AbstractStepSizeController
    dt0: float | None
    max_solver_steps: int
    projection: Projection | None
    baumgarte: Baumgarte | None


class DeprecatedLossKeywords(DeprecatedSimulationKeywords, total=False):
    """The keywords of `least_squares_loss` that ``simulation=`` replaces (deprecated)."""

    adjoint: diffrax.AbstractAdjoint | ForwardSensitivities


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
    simulation: SimulateOptions = SimulateOptions(),
    progress: bool = False,
    **deprecated: Unpack[DeprecatedSimulationKeywords],
) -> FitResult:
    """Fit ``params`` of ``system`` to ``experiments`` by least squares.

    **Arguments:**

    - ``system``: the [`System`][jaxlag.System] (constraints, dissipation and forces included).
    - ``params``: dict of free parameters with their starting values, or a `MultiStart`
      of several starting points (the best fit is returned).
    - ``experiments``: an `Experiment` or a list of them (equal shapes; batched by vmap).
    - ``observe``: ``observe(q, qd, [t], [args]) -> (k,)``, what was measured (default: ``q``).
      It matters: for a pendulum ``θ(t)`` depends only on ``g/l``, while the bob's Cartesian
      position ``l (sin θ, −cos θ)`` identifies ``g`` and ``l`` separately.
    - ``args``: fixed parameters, merged with ``params`` into the ``args`` the system sees.
    - ``transforms``: per-parameter `Positive` / `Bounded` reparameterizations.
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
    - ``shooting``: a `Shooting` (segments, continuity weight, starting guesses of the
      segment states, periodic coordinates); the default ``Shooting()`` is single shooting.
    - ``simulation``: the options of [`simulate`][jaxlag.simulate] for every simulation of the
      fit, a [`SimulateOptions`][jaxlag.SimulateOptions] (a plain dict works:
      ``simulation=dict(solver=diffrax.Dopri8(), max_steps=4096)``), forwarded untouched; one
      left out takes ``simulate``'s default. Its ``max_steps`` is the most integrator steps of
      one simulation; the fit's own ``max_steps`` is the optimizer's. The options the fit sets
      itself (``t0``, ``t1``, ``saveat``, ``adjoint``, ``throw``, ``checks``, ``event``,
      ``progress_meter``) are refused with the reason (``ValueError``).
    - ``progress``: show a tqdm progress bar (``pip install tqdm``).
    - ``solver``, ``stepsize_controller``, ``dt0``, ``max_solver_steps``, ``projection``,
      ``baumgarte``: deprecated (a ``DeprecationWarning``), removed in the next release; they are
      ``simulation``'s entries (``max_solver_steps`` is its ``max_steps``).

    Returns a `FitResult`; ``print(result)`` shows its `FitResult.summary`.
    """
    simulation = simulation_options(simulation, deprecated, "jl.fit", FIT_CONTROLS)
    if isinstance(params, MultiStart):
        options = dict(
            observe=observe, args=args, transforms=transforms, optimizer=optimizer, max_steps=max_steps,
            noise_std=noise_std, estimate_initial_state=estimate_initial_state, shooting=shooting,
            simulation=simulation, progress=progress,
        )  # fmt: skip
        return _multi_start(system, params, experiments, options)
    check_optimizer(optimizer)
    problem = _problem(
        system, params, experiments, observe, args, dict(transforms or {}), noise_std, estimate_initial_state,
        shooting, simulation,
    )  # fmt: skip
    try:
        if isinstance(optimizer, optx.AbstractGaussNewton):
            search = least_squares_loop(optimizer, problem, max_steps, progress)
        else:
            search = optax_loop(cast(optax.GradientTransformation, optimizer), problem, max_steps, progress)
    except (FloatingPointError, failures.SimulationError) as error:
        outliers = _outliers_at_start(problem)
        if outliers is None:
            raise
        raise type(error)(f"{error}\nAt the starting parameters, {outliers}.") from error
    return fit_result(problem, search, noise_std)


def _problem(
    system, params, experiments, observe, args, transforms, noise_std, estimate, shooting, simulation
) -> Problem:
    """The prologue of `fit`: its arguments checked, the `Model` built, the data and
    the starting free variables (unconstrained parameters, free segment states) ready."""
    batch = stack(experiments)
    check_options(transforms, params, shooting)
    observe = wrap_state_function(observe or _observe_coordinates, "observation function")
    real = jax.dtypes.canonicalize_dtype(float)  # on the host: no eager device conversions
    fixed = {k: np.asarray(v, real) if isinstance(v, (int, float)) else v for k, v in (args or {}).items()}
    params = {k: np.asarray(v, real) for k, v in params.items()}
    check_starts(params, transforms)
    check_observations(observe, batch, {**fixed, **params})
    mask = initial_mask(estimate, batch.q0.shape[-1])
    model = Model(
        system,
        observe,
        transforms,
        ParamSpec(tuple(params), tuple(jnp.shape(v) for v in params.values())),
        segments=int(shooting.segments),
        estimate_initial_state=mask is not None or estimate is True,
        initial_mask=mask,
        simulation=dict(simulation),
        periodic=shooting.periodic_coordinates,
    )
    ts_seg, starts = segment_grid(batch.ts, model.segments)
    segment_states = shooting.states
    if segment_states is None and model.segments > 1:
        segment_states = guess_states(model, batch.ts, batch.q0, batch.qd0, {**fixed, **params}, starts)
    elif segment_states is None:
        segment_states = (batch.q0[:, None], batch.qd0[:, None])
    segment_states = tuple(np.asarray(s, batch.q0.dtype) for s in segment_states)
    expected = (batch.ts.shape[0], model.segments, batch.q0.shape[-1])
    if segment_states[0].shape != expected or segment_states[1].shape != expected:
        raise ValueError(
            f"Shooting(states=(q, qd)) must have shape {expected} each (experiments, segments, "
            f"coordinates); got {segment_states[0].shape} and {segment_states[1].shape}."
        )
    noise = 1.0 if noise_std is None else float(noise_std)
    data = Data(fixed, batch.observations, noise, ts_seg, float(shooting.continuity_weight))
    free_states, fixed_states = model.split(segment_states)
    return Problem(model, data, {"params": unconstrained(model, params), **free_states}, fixed_states)


def _multi_start(system, starts: MultiStart, experiments, options) -> FitResult:
    """`fit` from each start of ``starts`` in turn; the best result, with all of them."""
    count = starts.count
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


def _outliers_at_start(problem: Problem) -> str | None:
    """The gross outliers of the residuals at the starting point (`gross_outliers`), for the
    message of a fit that failed; None when there are none or the residuals cannot be had."""
    try:
        r = residuals_and_jacobian(problem.model, problem.free, problem.data, problem.fixed_states).residuals
    except (FloatingPointError, ValueError, failures.SimulationError):
        return None
    data = problem.data
    observations, ts = np.asarray(data.observations), save_times(data.ts_seg)
    return gross_outliers(np.asarray(r), observations, float(data.noise), ts)


def least_squares_loss(
    system: System,
    params: dict[str, ArrayLike],
    experiments: Experiment | Sequence[Experiment],
    *,
    observe: Callable | None = None,
    args: dict | None = None,
    noise_std: float = 1.0,
    simulation: SimulateOptions = SimulateOptions(),
    **deprecated: Unpack[DeprecatedLossKeywords],
) -> Scalar:
    """The fit's loss ``½ Σ r²`` at physical ``params`` (single shooting, known initial states).

    Differentiable with ``jax.grad`` (the default ``adjoint``, as in [`simulate`][jaxlag.simulate])
    and ``jax.jacfwd`` (pass ``simulation=dict(adjoint=diffrax.ForwardMode())``); useful to check
    gradients or to drive your own optimizer. ``simulation``: the options of
    [`simulate`][jaxlag.simulate], as in [`fit`][jaxlag.fit], forwarded untouched, ``adjoint``
    included, and ``checks``: under your ``jax.jit`` the checks of the simulation (and, for a
    constrained system, of the projection of the initial state) are compiled into your program
    and raise through host callbacks by default; with
    ``simulation=dict(checks=jl.Checks(compiled=jl.NaNOnFailure()))`` a failed check or run
    makes the loss NaN instead, and the program holds no host callback (JAX's persistent cache
    can keep it, ``jax.export`` can serialize it). Eager calls raise either way. The keywords
    ``solver``, ``stepsize_controller``, ``dt0``, ``max_solver_steps`` (``simulation``'s
    ``max_steps``), ``adjoint``, ``projection`` and ``baumgarte`` are deprecated (a
    ``DeprecationWarning``), removed in the next release.
    """
    controlled = {k: v for k, v in FIT_CONTROLS.items() if k not in ("adjoint", "checks")}
    renamed = {**DEPRECATED_SIMULATION_KEYWORDS, "adjoint": "adjoint"}
    options = dict(simulation_options(simulation, deprecated, "jl.least_squares_loss", controlled, renamed))
    adjoint = options.pop("adjoint", ForwardSensitivities())
    checks = options.get("checks", Checks())
    if not isinstance(checks, Checks):
        raise TypeError(
            "jl.least_squares_loss(simulation=dict(checks=...)) takes a jl.Checks, e.g. "
            f"jl.Checks(compiled=jl.NaNOnFailure()); got {type(checks).__name__}."
        )
    batch = stack(experiments)
    observe = wrap_state_function(observe or _observe_coordinates, "observation function")
    spec = ParamSpec(tuple(params), tuple(jnp.shape(v) for v in params.values()))
    model = Model(system, observe, {}, spec, segments=1, estimate_initial_state=False, simulation=options)
    data = Data(dict(args or {}), batch.observations, noise_std, batch.ts[:, None, :], 0.0)
    if is_concrete(batch.observations) and not np.any(np.isfinite(np.asarray(batch.observations))):
        raise ValueError(
            "least_squares_loss: no observation is finite (all are NaN or inf): the loss would be "
            "0, a perfect fit of no data."
        )
    free = {"params": spec.ravel({k: jnp.asarray(v, float) for k, v in params.items()})}
    # The checks that no option reaches (the projection of a constrained initial state, a
    # System method in observe) follow the same choice, as inside simulate.
    with failures.on_failure(checks.compiled):
        r = model.residuals(free, data, (batch.q0[:, None], batch.qd0[:, None]), adjoint)
    return 0.5 * jnp.sum(r**2)
