"""Checks of [`fit`][jaxlag.fit]'s arguments, on the host before anything compiles: each raises
an error that names what is wrong and how to fix it."""

import jax
import numpy as np
import optax
import optimistix as optx

from .options import Bounded, Identity, Positive, Shooting


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
