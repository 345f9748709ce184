r"""What a fit can vouch for, at the optimum: the covariance of the Gauss–Newton approximation,
the directions the data cannot determine, the warnings, and `FitResult`.

With the Jacobian ``J = ∂r/∂θ`` in physical parameters (then the free segment states),
``Cov = σ̂² (JᵀJ)⁻¹``, where ``σ̂² = |r|²/(N − p)`` is estimated from the residuals unless
``noise_std`` is given (then ``Cov = (JᵀJ)⁻¹``). The inverse is rank-revealing
(`rank_revealing`).
"""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from .. import _compile as compilation
from .._conventions import as_jax_array
from .._custom_types import Scalar
from .combinations import IdentifiableCombination, identifiable_combinations
from .data import save_times
from .diagnostics import gross_outliers, misfit
from .loops import Search
from .model import Problem, residuals_and_jacobian
from .options import Bounded, FitWarning, SegmentStates
from .summary import summary_text


class FitResult(eqx.Module):
    """Outcome of `fit`.

    ``params``: fitted parameters (physical values, same structure as the initial guess).
    ``standard_errors``: same structure; ``covariance``: (p, p) over the free scalars named in
    ``names`` (the parameters in the order they were given, ``"k[1]"`` for an entry of an array
    parameter). ``initial_states``: fitted ``(q0, qd0)`` per experiment when estimated.
    ``loss_history``: ``ℓ`` after each optimizer step (index 0 is the starting point).
    ``segment_states``: ``(q, qd)`` of shape (E, S, n), the state each shooting segment starts from.

    What the fit can vouch for (all computed at the optimum, see `fit`):

    - ``standard_errors``: ``inf`` for a parameter the data cannot determine (it has a
      component along a flat direction of the residuals) or that does not affect them.
      ``covariance``: such a parameter has ``inf`` on the diagonal and NaN elsewhere in its
      row and column. ``correlation``: ``Cov_ij / √(Cov_ii Cov_jj)``, NaN rows and columns
      for those parameters.
    - ``undetermined``, ``insensitive``: the names of those parameters (``"k[1]"`` for an
      entry of an array parameter; estimated initial states as ``"q0[0] of experiment 0"``).
    - ``identifiable``: the combinations of undetermined parameters that the data do
      determine, each an [`IdentifiableCombination`][jaxlag.IdentifiableCombination]: a
      monomial ``Π θ_j^{a_j}`` (``g^1 · l^-1`` for a pendulum observed through ``θ``) with its
      value and standard error; empty when every parameter is determined.
    - ``at_bound``: parameters that end within ``1e-6 (upper − lower)`` of a `Bounded`
      transform's bound.
    - ``residual_std``: the standard deviation of the residuals, ``√(Σ r²/(N − p))`` in the
      units of the observations. ``reduced_chi2``: ``Σ (r/σ)²/(N − p)`` when ``noise_std`` is
      given (else None); about ``1 ± √(2/(N − p))`` for a good fit. ``chi2``: ``Σ (r/σ)²``
      (``σ = 1`` without ``noise_std``, then the sum of squared residuals), ``dof``: ``N − p``
      (``N`` finite observations, ``p`` free scalars), ``noise_std``: the one given.
    - ``warnings``: the texts of the `FitWarning` s the fit issued.
    - ``initial_state_errors``: standard errors of the estimated initial states (same
      structure as ``initial_states``), None when they are not estimated.
    - ``converged``: the optimizer's stopping criterion was met; it says nothing about the
      items above (a fit can converge to a local minimum, or to one point of a flat valley).

    ``str(result)`` (``print(result)``) is `summary`: the parameters with their standard
    errors, the strong correlations, the identifiable combinations, the goodness of fit and
    the warnings; ``repr`` is equinox's.
    """

    params: dict[str, Float[np.ndarray | Array, "..."]]
    standard_errors: dict[str, Float[Array, "..."]]
    covariance: Float[Array, "p p"]
    residual_std: Scalar
    loss_history: Float[np.ndarray, " steps"]
    initial_states: tuple[
        Float[np.ndarray | Array, "experiments n"], Float[np.ndarray | Array, "experiments n"]
    ]
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
    start_params: dict[str, Float[Array, "starts ..."]] | None = None
    identifiable: tuple[IdentifiableCombination, ...] = ()
    chi2: float | None = None
    dof: int | None = None
    noise_std: float | None = None
    names: tuple[str, ...] = ()

    def summary(self, min_correlation: float = 0.1) -> str:
        """A readable report, as statsmodels' and lmfit's: each parameter's value ± standard
        error, the correlations with ``|ρ| ≥ min_correlation``, the identifiable combinations,
        ``χ²``, the residual standard deviation, ``dof``, whether the optimizer converged and
        in how many steps, the starts of a `MultiStart`, and the warnings."""
        return summary_text(self, min_correlation)

    def __str__(self) -> str:
        return self.summary()


def fit_result(problem: Problem, search: Search, noise_std: float | None) -> FitResult:
    """The `FitResult` at the end of ``search``, its `FitWarning` s issued.

    ``χ² = |r|²`` over ``N`` finite observations and ``p`` free scalars (``dof = N − p``):
    ``σ̂² = χ²/dof``, ``residual_std = σ̂`` without ``noise_std``; with it, ``σ̂² = 1``,
    ``residual_std = noise_std √(χ²/dof)`` and ``reduced_chi2 = χ²/dof``.
    """
    model, free = problem.model, search.free
    flat = np.concatenate([np.ravel(np.asarray(leaf)) for leaf in jax.tree.leaves(free)])
    linearization = search.linearization
    if linearization is None or not np.array_equal(flat, np.asarray(linearization.point)):
        linearization = residuals_and_jacobian(model, free, problem.data, problem.fixed_states, search.lean)
    # else the last step was taken at (and accepted) this point: its linearization is the one here
    fitted, jac, x, states = jax.device_get(
        _summary(model, free, problem.fixed_states, linearization.jacobian)
    )
    r, jac, x = np.asarray(linearization.residuals), np.asarray(jac), np.asarray(x)
    dof = max(int(np.sum(np.isfinite(np.asarray(problem.data.observations)))) - flat.size, 1)
    chi2 = float(np.sum(r**2))
    sigma2 = chi2 / dof if noise_std is None else 1.0
    residual_std = np.sqrt(sigma2) if noise_std is None else float(noise_std) * np.sqrt(chi2 / dof)
    reduced_chi2 = None if noise_std is None else chi2 / dof
    names = _column_names(model, np.shape(states[0])[0], np.shape(states[0])[-1])
    covariance, errors, insensitive, null, generalized = rank_revealing(jac, x, sigma2, names)
    p = len(model.spec.ravel(fitted))
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = covariance / np.sqrt(np.outer(np.diag(covariance), np.diag(covariance)))
    correlation[~np.isfinite(errors), :] = np.nan
    correlation[:, ~np.isfinite(errors)] = np.nan
    messages = [f"{names[j]} does not affect the residuals" for j in insensitive]
    messages += describe_null(null, x, names)
    at_bound, bound_messages = _at_bound(model.transforms, fitted)
    messages += bound_messages
    observations, noise = np.asarray(problem.data.observations), float(problem.data.noise)
    outliers = gross_outliers(r, observations, noise, save_times(problem.data.ts_seg))
    messages += [] if outliers is None else [outliers]
    if noise_std is not None and reduced_chi2 is not None and reduced_chi2 > 1 + 5 * np.sqrt(2 / dof):
        messages.append(
            f"the fit ends with reduced χ² = {reduced_chi2:.3g} (residual std {residual_std:.3g} for "
            f"noise_std {float(noise_std):.3g}), beyond 1 + 5·√(2/{dof}) = "
            f"{1 + 5 * np.sqrt(2 / dof):.3g}: the fit ends at a local minimum or the model does not "
            "describe the data; try another start"
        )
    elif noise_std is None and outliers is None:
        messages += [m for m in (misfit(r, observations),) if m is not None]
    for message in messages:
        warnings.warn(f"jl.fit: {message}.", FitWarning, stacklevel=3)
    return FitResult(
        fitted,
        model.spec.unravel(as_jax_array(errors[:p])),
        as_jax_array(covariance[:p, :p]),
        as_jax_array(residual_std),
        np.asarray(search.history),
        (states[0][:, 0], states[1][:, 0]),
        search.num_steps,
        search.converged,
        states,
        correlation=as_jax_array(correlation[:p, :p]),
        reduced_chi2=reduced_chi2,
        undetermined=tuple(names[j] for j in np.flatnonzero(~np.isfinite(errors)) if j not in insensitive),
        insensitive=tuple(names[j] for j in insensitive),
        at_bound=at_bound,
        warnings=tuple(messages),
        initial_state_errors=_initial_state_errors(model, errors[p:], states),
        identifiable=identifiable_combinations(null, x, generalized, names),
        chi2=chi2,
        dof=dof,
        noise_std=None if noise_std is None else float(noise_std),
        names=tuple(names[:p]),
    )


@compilation.lean_jit
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


def _at_bound(transforms, fitted) -> tuple[tuple[str, ...], list[str]]:
    """The parameters within ``1e-6 (upper − lower)`` of a `Bounded` bound, and the
    warnings that say so."""
    at_bound, messages = [], []
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
    return tuple(at_bound), messages


def _initial_state_errors(model, errors, states):
    """The standard errors of the estimated initial states ``(q0, qd0)`` (E, n) each, from the
    ``errors`` of the free variables after the parameters; None when they are not estimated."""
    if not model.estimate_initial_state:
        return None
    if model.initial_mask is None:
        state_errors = errors.reshape((2, *np.shape(states[0])))
        return as_jax_array(state_errors[0][:, 0]), as_jax_array(state_errors[1][:, 0])
    # Known entries: standard error 0; estimated ones in ravel order (q entries, then qd).
    shape = np.shape(states[0][:, 0])
    q_se, qd_se, start = np.zeros(shape), np.zeros(shape), 0
    for target, indices in zip((q_se, qd_se), model.initial_mask):
        size = shape[0] * len(indices)
        target[:, list(indices)] = errors[start : start + size].reshape(shape[0], len(indices))
        start += size
    return as_jax_array(q_se), as_jax_array(qd_se)


def _column_names(model, num_experiments, n) -> list[str]:
    """The name of each free scalar, in the order of the columns of ``J``."""
    names = []
    for key, shape in zip(model.spec.keys, model.spec.shapes):
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


def rank_revealing(jac, x, sigma2, names):
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
    null vectors in physical units, generalized inverse)``: the last is ``σ² (JᵀJ)⁺`` over the
    sensitive variables (zero elsewhere), finite, for the combinations the data determine
    (`jaxlag._fit.combinations`).
    """
    eps = np.finfo(jac.dtype).eps
    norms = np.linalg.norm(jac, axis=0)
    relative = norms * np.maximum(np.abs(x), 1.0)  # change of r for a change of x by max(|x|, 1)
    scale = relative.max() if relative.size and relative.max() > 0 else 1.0
    insensitive = np.flatnonzero(~(relative > np.sqrt(eps) * scale))
    active = np.flatnonzero(relative > np.sqrt(eps) * scale)
    p = jac.shape[1]
    covariance = np.full((p, p), np.nan)
    generalized = np.zeros((p, p))
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
        generalized[np.ix_(active, active)] = sub
        ok = active[~undetermined]
        errors[ok] = np.sqrt(np.diag(covariance)[ok])
        bad = active[undetermined]
        covariance[bad, :] = np.nan
        covariance[:, bad] = np.nan
    covariance[insensitive, :] = np.nan
    covariance[:, insensitive] = np.nan
    for j in np.flatnonzero(~np.isfinite(errors)):
        covariance[j, j] = np.inf
    return covariance, errors, insensitive, null, generalized


def describe_null(null, x, names) -> list[str]:
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
