r"""Whether the residuals look like noise, on the host after a fit: gross outliers, and
residuals far above the noise level the data themselves show.

The noise level of each experiment ``e`` and observed channel ``k`` is estimated from the data
alone, without the model: a smooth signal sampled finely has small differences of order ``m``,
while white noise of standard deviation ``σ`` gives ``Var(Δᵐy) = C(2m, m) σ²``. So

    σ_d = min over m = 1, 2, 3 of  1.4826 · MAD(Δᵐy) / √C(2m, m)

(MAD: the median absolute deviation from the median, robust to a few outliers; the signal can
only add to the spread, so each order over-estimates ``σ``, and the smallest is the least
contaminated). It is floored at ``1e-6 · median |y|``: residuals that small are the
integrator's, not a misfit (data that are a low-order polynomial of time have differences of
zero). Only the observation residuals enter, not the continuity residuals of multiple shooting.
"""

import math

import numpy as np

#: A residual this many robust standard deviations from the median residual is a gross outlier.
OUTLIER_THRESHOLD = 100.0
#: Residuals whose RMS is this many times the differences' noise estimate are not noise ...
MISFIT_RATIO = 5.0
#: ... when neighbouring residuals are also this correlated (lag-1 autocorrelation).
MISFIT_AUTOCORRELATION = 0.5
_MAD = 1.4826  # MAD → standard deviation for normal data
_FLOOR = 1e-6


def _mad(x: np.ndarray) -> float:
    return _MAD * float(np.median(np.abs(x - np.median(x)))) if x.size else 0.0


def noise_from_differences(observations: np.ndarray) -> np.ndarray:
    """``σ_d`` of each experiment and observed channel, shape (E, k), from the finite
    observations (E, T, k) in time order (NaN for a channel with fewer than 4 of them)."""
    e_count, _, k_count = observations.shape
    sigma = np.full((e_count, k_count), np.nan)
    for e in range(e_count):
        for k in range(k_count):
            y = observations[e, :, k]
            y = y[np.isfinite(y)]
            if y.size < 4:
                continue
            estimates = [
                _mad(np.diff(y, m)) / math.sqrt(math.comb(2 * m, m)) for m in (1, 2, 3) if y.size - m >= 3
            ]
            sigma[e, k] = max(min(estimates), _FLOOR * float(np.median(np.abs(y))))
    return sigma


def _observation_residuals(residuals: np.ndarray, observations: np.ndarray) -> np.ndarray:
    """The residuals of the observations (E, T, k), NaN where the observation is missing."""
    r = np.asarray(residuals)[: observations.size].reshape(observations.shape)
    return np.where(np.isfinite(observations), r, np.nan)


def gross_outliers(residuals, observations, noise, ts, limit: int = 3) -> str | None:
    """Words for the observations whose residual is more than `OUTLIER_THRESHOLD` robust
    standard deviations from the median residual of its experiment and channel (the larger of
    the residuals' own MAD-based spread and ``σ_d / noise``); None when there is none.

    ``residuals``: the weighted residuals ``(y_model − y_observed)/noise``, observations first
    (raveled (E, T, k)); ``ts``: the save times (E, T)."""
    observations = np.asarray(observations)
    r = _observation_residuals(residuals, observations)
    sigma = noise_from_differences(observations) / noise
    found = []
    for e in range(r.shape[0]):
        for k in range(r.shape[2]):
            column = r[e, :, k]
            finite = column[np.isfinite(column)]
            if finite.size < 4 or not np.isfinite(sigma[e, k]):
                continue
            centre, scale = float(np.median(finite)), max(_mad(finite), float(sigma[e, k]))
            if scale <= 0:
                continue
            z = np.abs(column - centre) / scale
            for i in np.flatnonzero(z > OUTLIER_THRESHOLD):
                found.append((float(z[i]), e, int(i), k))
    if not found:
        return None
    found.sort(reverse=True)
    words = [
        f"experiment {e}, observations[{i}, {k}] = {observations[e, i, k]:.6g} at t = {ts[e, i]:.6g} "
        f"(its residual is {z:.2g} robust standard deviations from the median)"
        for z, e, i, k in found[:limit]
    ]
    more = f", and {len(found) - limit} more" if len(found) > limit else ""
    return (
        f"the data hold {'a gross outlier' if len(found) == 1 else f'{len(found)} gross outliers'}: "
        + "; ".join(words)
        + more
        + ". One wrong observation pulls a least-squares fit away from all the others: correct it, or "
        "mark it missing with NaN"
    )


def misfit(residuals, observations) -> str | None:
    """Words for residuals that are not noise: their RMS, in units of each channel's ``σ_d``,
    above `MISFIT_RATIO` and their lag-1 autocorrelation above `MISFIT_AUTOCORRELATION`
    (residuals of a local minimum or of a wrong model are smooth functions of time, noise is
    not); None when they look like noise. For fits without ``noise_std`` (residuals in the
    units of the data)."""
    observations = np.asarray(observations)
    sigma = noise_from_differences(observations)
    r = _observation_residuals(residuals, observations) / sigma[:, None, :]
    r = np.where(np.isfinite(r), r, 0.0)  # missing observations and channels with too few
    count = int(np.sum(np.isfinite(observations) & np.isfinite(sigma)[:, None, :]))
    total = float(np.sum(r**2))
    if count == 0 or total == 0:
        return None
    ratio = math.sqrt(total / count)
    autocorrelation = float(np.sum(r[:, 1:] * r[:, :-1])) / total
    if ratio <= MISFIT_RATIO or autocorrelation <= MISFIT_AUTOCORRELATION:
        return None
    level = float(np.sqrt(np.nanmean(sigma**2)))
    return (
        f"the residuals are not noise: their RMS is {ratio:.3g} times the noise level the data "
        f"themselves show (≈ {level:.3g}, from their differences), and neighbouring residuals are "
        f"correlated (lag-1 autocorrelation {autocorrelation:.2f}): the fit may have stopped at a "
        "local minimum, or the model does not describe the data; try other starts with "
        "jl.MultiStart, or give noise_std"
    )
