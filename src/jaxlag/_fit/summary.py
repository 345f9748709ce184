"""`FitResult.summary`: the fit as a readable report (parameters ± standard errors, strong
correlations, identifiable combinations, goodness of fit, warnings), as statsmodels and lmfit
print theirs."""

import math

import numpy as np


def _number(value: float, error: float | None = None) -> str:
    """``value`` to the digits its standard error supports (two significant digits of the
    error), or six significant digits without a finite positive error."""
    if error is None or not math.isfinite(error) or error <= 0 or not math.isfinite(value) or value == 0:
        return f"{value:.6g}"
    digits = math.floor(math.log10(abs(value))) - math.floor(math.log10(error)) + 2
    return f"{value:.{min(max(digits, 2), 12)}g}"


def _entries(result):
    """``(name, value, standard error)`` of each free scalar parameter, in covariance order."""
    rows = []
    for key in dict.fromkeys(name.split("[")[0] for name in result.names) or result.params:
        value = np.ravel(np.asarray(result.params[key]))
        error = np.ravel(np.asarray(result.standard_errors[key]))
        shape = np.shape(result.params[key])
        labels = [key] if shape == () else [f"{key}[{', '.join(map(str, i))}]" for i in np.ndindex(*shape)]
        rows += [(label, float(v), float(e)) for label, v, e in zip(labels, value, error)]
    return rows


def _parameter_lines(result) -> list[str]:
    rows = _entries(result)
    width = max(len(name) for name, _, _ in rows)
    lines = []
    for name, value, error in rows:
        note = ""
        if name in result.insensitive:
            note = "   (does not affect the residuals)"
        elif name in result.undetermined:
            note = "   (not determined by the data)"
        elif name in result.at_bound:
            note = "   (at a bound)"
        shown = f"{_number(value, error)} ± {error:.2g}" if math.isfinite(error) else f"{value:.6g} ± inf"
        lines.append(f"  {name:<{width}}  {shown}{note}")
    return lines


def _correlation_lines(result, min_correlation: float) -> list[str]:
    if result.correlation is None:
        return []
    names = [name for name, _, _ in _entries(result)]
    corr = np.asarray(result.correlation)
    pairs = [
        (abs(corr[i, j]), names[i], names[j], corr[i, j])
        for i in range(len(names))
        for j in range(i + 1, len(names))
        if np.isfinite(corr[i, j]) and abs(corr[i, j]) >= min_correlation
    ]
    if not pairs:
        return []
    lines = [f"Correlations (|ρ| ≥ {min_correlation:g}):"]
    lines += [f"  ρ({a}, {b}) = {value:+.3f}" for _, a, b, value in sorted(pairs, reverse=True)]
    return lines


def _fit_lines(result) -> list[str]:
    steps = f"{result.num_steps} step{'s' if result.num_steps != 1 else ''}"
    head = f"converged in {steps}" if result.converged else f"not converged after {steps}"
    history = np.asarray(result.loss_history)
    lines = [f"jl.fit: {head}; loss ½Σr² {history[0]:.4g} → {history[-1]:.4g}"]
    if result.dof is not None:
        lines.append(f"  {result.dof} degrees of freedom (finite observations − free scalars)")
    if result.noise_std is not None and result.reduced_chi2 is not None:
        lines.append(
            f"  χ² = {result.chi2:.4g}, reduced χ² = {result.reduced_chi2:.4g} (noise_std "
            f"{result.noise_std:.4g}); residual std {float(result.residual_std):.4g}"
        )
    else:
        std = float(result.residual_std)
        lines.append(f"  residual std {std:.4g} (the noise, estimated from the residuals)")
    return lines


def summary_text(result, min_correlation: float = 0.1) -> str:
    """The report of `FitResult.summary`."""
    lines = _fit_lines(result)
    lines += ["Parameters (value ± standard error):", *_parameter_lines(result)]
    if result.initial_state_errors is not None:
        lines.append("  initial states estimated: see initial_states and initial_state_errors")
    lines += _correlation_lines(result, min_correlation)
    if result.identifiable:
        lines.append("Identifiable combinations (value ± standard error):")
        width = max(len(c.name) for c in result.identifiable)
        lines += [
            f"  {c.name:<{width}}  {_number(c.value, c.standard_error)} ± {c.standard_error:.2g}"
            for c in result.identifiable
        ]
    if result.start_losses is not None:
        losses = np.asarray(result.start_losses)
        lines.append(
            f"MultiStart: {losses.size} starts, the best is start {int(np.argmin(losses))}; final losses "
            + ", ".join(f"{v:.4g}" for v in losses)
        )
    if result.warnings:
        lines += ["Warnings:", *(f"  - {message}." for message in result.warnings)]
    return "\n".join(lines)
