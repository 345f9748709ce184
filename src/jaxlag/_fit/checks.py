"""Checks of [`fit`][jaxlag.fit]'s arguments, on the host before anything compiles: each raises
an error that names what is wrong and how to fix it."""

import warnings
from collections.abc import Mapping
from typing import Any, cast

import jax
import numpy as np
import optax
import optimistix as optx

from .._options import SimulateOptions, check_option_names
from .options import Bounded, Identity, Positive, Shooting

#: The options of jl.simulate that the fit sets itself, and why a user's value makes no sense.
FIT_CONTROLS = {
    "t0": "each experiment is integrated over its own save times ts",
    "t1": "each experiment is integrated over its own save times ts",
    "saveat": "the simulation saves at each experiment's save times ts (and the shooting segments' ends)",
    "adjoint": (
        "the fit differentiates the simulation itself: forward mode (diffrax.ForwardMode) for the "
        "Jacobian of the least-squares solvers, jl.ForwardSensitivities() for optax "
        "(jl.least_squares_loss takes an adjoint)"
    ),
    "throw": "the fit raises a failed simulation itself, naming the parameters being tried",
    "checks": (
        "the fit checks its data once, on the host, and projects every initial state onto the constraints"
    ),
    "event": (
        "a terminating diffrax event would end the simulation before the last observation "
        "(conditions that switch the motion go in events=jl.Events(...))"
    ),
    "progress_meter": "one meter per simulation; jl.fit(progress=True) shows the fit's progress",
}

#: The keywords of jl.fit that simulation= replaces (deprecated), and their SimulateOptions names.
DEPRECATED_SIMULATION_KEYWORDS = {
    "solver": "solver",
    "stepsize_controller": "stepsize_controller",
    "dt0": "dt0",
    "max_solver_steps": "max_steps",
    "projection": "projection",
    "baumgarte": "baumgarte",
}


def check_options(transforms, params, shooting) -> None:
    """``transforms`` name fitted parameters, ``shooting`` is a `Shooting`."""
    unknown = set(transforms) - set(params)
    if unknown:
        raise ValueError(f"transforms name parameters that are not being fitted: {sorted(unknown)}.")
    if not isinstance(shooting, Shooting):
        raise TypeError(
            f"shooting must be a jl.Shooting, e.g. shooting=jl.Shooting(segments=4); got {shooting!r}."
        )


def check_observations(observe, batch, args) -> None:
    """``observe`` returns what was observed per time (shape (k,)), and something was observed."""
    out = jax.eval_shape(lambda q, qd: observe(q, qd, t=batch.ts[0, 0], args=args), batch.q0[0], batch.qd0[0])
    if out.shape != batch.observations.shape[2:]:
        raise ValueError(
            f"The observation function returns shape {out.shape} per time, but the observations "
            f"have shape {batch.observations.shape[2:]} per time."
        )
    if not np.any(np.isfinite(np.asarray(batch.observations))):
        raise ValueError("All observations are NaN: nothing to fit.")


def initial_mask(estimate, n):
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


def check_starts(params, transforms) -> None:
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


def check_optimizer(optimizer) -> bool:
    """Whether ``optimizer`` is an optimistix least-squares solver that `fit` can step
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


def simulation_options(
    simulation: Mapping[str, Any],
    deprecated: Mapping[str, Any],
    caller: str,
    controlled: Mapping[str, str],
    renamed: Mapping[str, str] = DEPRECATED_SIMULATION_KEYWORDS,
) -> SimulateOptions:
    """The options of [`simulate`][jaxlag.simulate] that ``caller`` forwards to it: ``simulation``
    (names checked, those in ``controlled`` refused with the reason) merged with the deprecated
    keywords ``deprecated`` (a ``DeprecationWarning`` each, naming the new spelling; ``renamed``
    maps each to its option)."""
    if not isinstance(simulation, Mapping):
        raise TypeError(
            f"{caller}(simulation=...) takes a dict of jl.simulate's options (a jl.SimulateOptions), "
            f"e.g. simulation=dict(solver=diffrax.Dopri8(), max_steps=4096); got {type(simulation).__name__}."
        )
    try:
        check_option_names(simulation, "simulate")
    except TypeError as error:
        raise TypeError(f"{caller}(simulation=...): {error} Its keys are jl.simulate's options.") from None
    refused = [name for name in simulation if name in controlled]
    if refused:
        raise ValueError(
            f"{caller}(simulation=...) sets {', '.join(map(repr, refused))} itself: "
            + "; ".join(f"{name}: {controlled[name]}" for name in refused)
            + "."
        )
    options = dict(simulation)
    for keyword, value in deprecated.items():
        if keyword not in renamed:
            raise TypeError(f"{caller}() got an unexpected keyword argument {keyword!r}.")
        name = renamed[keyword]
        if name in options:
            raise TypeError(
                f"{caller}(): {keyword}= and simulation={{{name!r}: ...}} give the same option twice."
            )
        spelling = f"simulation=dict({name}=...)"
        warnings.warn(
            f"{caller}({keyword}=...) is deprecated and will be removed in the next release: "
            f"pass {spelling} (the options of jl.simulate, forwarded to it untouched).",
            DeprecationWarning,
            stacklevel=3,
        )
        options[name] = value
    return cast(SimulateOptions, options)
