"""jl.fit reports what the data cannot determine, how well it fits, and refuses bad input."""

import contextlib
import re
import warnings

import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest

import jaxlag as jl

TS = jnp.linspace(0.0, 2.0, 21)
Q0, QD0 = jnp.array([0.9]), jnp.array([0.0])
TRUE = {"g": 9.81, "l": 0.8, "m": 1.0}


def pendulum(q, qd, args):
    m, g, l = args["m"], args["g"], args["l"]
    return 0.5 * m * l**2 * qd[0] ** 2 + m * g * l * jnp.cos(q[0])


PENDULUM = jl.System(pendulum)


@contextlib.contextmanager
def without_type_checks():
    """jaxlag's own checks, as a user without a run-time type checker meets them: the suite's
    checker (tests/conftest.py) would refuse a wrongly typed argument first."""
    previous = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", previous)


THETA = np.asarray(jl.simulate(PENDULUM, Q0, QD0, TS, args=TRUE).q)


def bob(q, qd, args):
    return args["l"] * jnp.array([jnp.sin(q[0]), -jnp.cos(q[0])])


def fit_recording(*args, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = jl.fit(*args, **kwargs)
    return result, [str(w.message) for w in caught if issubclass(w.category, jl.FitWarning)]


def test_theta_alone_reports_g_and_l_undetermined():
    result, messages = fit_recording(
        PENDULUM, {"g": 11.0, "l": 0.7}, jl.Experiment(TS, THETA, Q0, QD0), args={"m": 1.0}
    )
    # The ratio is fitted (noise-free data, integrator at rtol 1e-10) ...
    ratio = result.params["g"] / result.params["l"]
    assert abs(ratio / (TRUE["g"] / TRUE["l"]) - 1) < 1e-7
    # ... but neither g nor l: infinite standard errors, named, with the determined combination.
    assert np.isinf(result.standard_errors["g"]) and np.isinf(result.standard_errors["l"])
    assert result.undetermined == ("g", "l")
    assert messages == [
        "jl.fit: only g/l is determined by the data: g and l can be scaled together without "
        "changing the residuals."
    ]
    assert result.warnings == tuple(m.removeprefix("jl.fit: ").removesuffix(".") for m in messages)
    assert np.all(np.isnan(result.correlation))


def test_parameters_that_do_not_affect_the_residuals_are_named():
    # The mass cancels from the motion; c is never read by the system.
    result, messages = fit_recording(
        PENDULUM, {"g": 11.0, "m": 2.0, "c": 1.0}, jl.Experiment(TS, THETA, Q0, QD0), args={"l": 0.8}
    )
    assert abs(result.params["g"] / TRUE["g"] - 1) < 1e-7
    assert np.isfinite(result.standard_errors["g"])
    assert np.isinf(result.standard_errors["m"]) and np.isinf(result.standard_errors["c"])
    assert set(result.insensitive) == {"m", "c"}
    assert sorted(messages) == [
        "jl.fit: c does not affect the residuals.",
        "jl.fit: m does not affect the residuals.",
    ]


def test_identifiable_fit_has_finite_errors_correlations_and_no_warning():
    sigma = 0.01
    rng = np.random.default_rng(0)
    clean = np.asarray(jax.vmap(lambda q: bob(q, None, TRUE))(jnp.asarray(THETA)))
    data = clean + sigma * rng.standard_normal(clean.shape)
    result, messages = fit_recording(
        PENDULUM,
        {"g": 11.0, "l": 0.7},
        jl.Experiment(TS, data, Q0, QD0),
        observe=bob,
        args={"m": 1.0},
        noise_std=sigma,
    )
    assert messages == [] and result.warnings == ()
    se = np.array([result.standard_errors["g"], result.standard_errors["l"]])
    assert np.all(np.isfinite(se)) and np.all(se > 0)
    np.testing.assert_allclose(np.sqrt(np.diag(result.covariance)), se, rtol=1e-12)
    corr = np.asarray(result.correlation)
    np.testing.assert_allclose(np.diag(corr), 1.0, rtol=1e-12)
    assert abs(corr[0, 1]) < 1
    # 42 observations, 2 parameters: reduced χ² ~ 1 ± √(2/40); residual std against σ.
    assert result.reduced_chi2 is not None and abs(result.reduced_chi2 - 1) < 5 * np.sqrt(2 / 40)
    assert abs(float(result.residual_std) / sigma - 1) < 0.3


def test_local_minimum_and_bound_are_warned():
    sigma = 0.01
    experiment = jl.Experiment(TS, THETA, Q0, QD0)
    # Bounds that exclude the truth (g = 9.81): g is pushed onto the upper bound.
    result, messages = fit_recording(
        PENDULUM,
        {"g": 7.0},
        experiment,
        args={"m": 1.0, "l": 0.8},
        transforms={"g": jl.Bounded(5.0, 8.0)},
        noise_std=sigma,
        max_steps=60,
    )
    assert result.at_bound == ("g",)
    assert any("g = 8 ends at a bound of Bounded(5.0, 8.0)" in m for m in messages)
    assert result.reduced_chi2 is not None and result.reduced_chi2 > 1 + 5 * np.sqrt(2 / 20)
    assert any("local minimum or the model does not describe the data" in m for m in messages)


def test_bad_input_is_named():
    good = jl.Experiment(TS, THETA, Q0, QD0)
    cases = [
        (
            jl.Experiment(TS, np.where(np.arange(21)[:, None] == 3, np.inf, THETA), Q0, QD0),
            {"g": 9.0},
            {},
            r"Experiment 0: observations\[3, 0\] \(time index 3, t = 0.3.*\) is inf",
        ),
        (
            jl.Experiment(np.append(np.asarray(TS[:-1]), np.inf), THETA, Q0, QD0),
            {"g": 9.0},
            {},
            r"Experiment 0: save time ts\[20\] = inf is not finite",
        ),
        (jl.Experiment(TS, THETA, jnp.array([np.nan]), QD0), {"g": 9.0}, {}, r"Experiment 0: q0\[0\] = nan"),
        (jl.Experiment(TS, THETA, jnp.array([0.9, 0.0]), QD0), {"g": 9.0}, {}, r"Experiment 0: q0 and qd0"),
        (
            good,
            {"g": -1.0},
            {"g": jl.Positive()},
            r"starting value g = -1.0 is outside the domain \(0, inf\)",
        ),
        (
            good,
            {"g": 20.0},
            {"g": jl.Bounded(5.0, 15.0)},
            r"g = 20.0 is outside the domain the open interval \(5.0, 15.0\)",
        ),
        (good, {"g": 15.0}, {"g": jl.Bounded(5.0, 15.0)}, r"g = 15.0 is outside"),
    ]
    for experiment, start, transforms, match in cases:
        with pytest.raises(ValueError, match=match):
            jl.fit(PENDULUM, start, experiment, args={"m": 1.0, "l": 0.8}, transforms=transforms)
    with pytest.raises(ValueError, match=r"Experiment 1: q0 has 2 entries, but experiment 0's q0 has 1"):
        jl.fit(
            PENDULUM,
            {"g": 9.0},
            [good, jl.Experiment(TS, THETA, jnp.zeros(2), jnp.zeros(2))],
            args={"m": 1.0, "l": 0.8},
        )
    missing = jl.Experiment(TS, np.full_like(THETA, np.nan), Q0, QD0)
    with pytest.raises(ValueError, match="no observation is finite"):
        jl.least_squares_loss(PENDULUM, {"g": 9.0}, missing, args={"m": 1.0, "l": 0.8})


def test_estimated_initial_state_has_standard_errors():
    sigma = 0.01
    rng = np.random.default_rng(1)
    clean = np.asarray(jax.vmap(lambda q: bob(q, None, TRUE))(jnp.asarray(THETA)))
    data = clean + sigma * rng.standard_normal(clean.shape)
    result, messages = fit_recording(
        PENDULUM,
        {"g": 11.0},
        jl.Experiment(TS, data, jnp.array([0.8]), jnp.array([0.1])),
        observe=bob,
        args={"m": 1.0, "l": 0.8},
        noise_std=sigma,
        estimate_initial_state=True,
    )
    assert messages == []
    assert result.initial_state_errors is not None
    q_se, qd_se = (np.asarray(a) for a in result.initial_state_errors)
    assert q_se.shape == qd_se.shape == (1, 1)
    assert np.all(np.isfinite(q_se)) and np.all(q_se > 0) and np.all(qd_se > 0)
    # The truth (0.9, 0) within 5 standard errors of the estimate (one draw, 3 free scalars).
    q0, qd0 = (np.asarray(a) for a in result.initial_states)
    assert abs(q0[0, 0] - 0.9) < 5 * q_se[0, 0] and abs(qd0[0, 0]) < 5 * qd_se[0, 0]
    np.testing.assert_allclose(np.sqrt(np.asarray(result.covariance)[0, 0]), result.standard_errors["g"])


def test_partial_initial_state_theta0_free_thetadot0_known():
    sigma = 0.01
    rng = np.random.default_rng(2)
    data = THETA + sigma * rng.standard_normal(THETA.shape)
    mask = (jnp.array([True]), jnp.array([False]))  # θ0 estimated, θ̇0 = 0 known
    result, messages = fit_recording(
        PENDULUM,
        {"g": 11.0},
        jl.Experiment(TS, data, jnp.array([0.7]), jnp.array([0.0])),
        args={"m": 1.0, "l": 0.8},
        noise_std=sigma,
        estimate_initial_state=mask,
    )
    assert messages == []
    q0, qd0 = (np.asarray(a) for a in result.initial_states)
    assert qd0[0, 0] == 0.0  # known, untouched
    assert result.initial_state_errors is not None
    q_se, qd_se = (np.asarray(a) for a in result.initial_state_errors)
    assert qd_se[0, 0] == 0.0 and 0 < q_se[0, 0] < 0.01
    assert abs(q0[0, 0] - 0.9) < 5 * q_se[0, 0]
    assert abs(result.params["g"] - 9.81) < 5 * result.standard_errors["g"]
    with without_type_checks(), pytest.raises(ValueError, match=r"qd_mask must be a boolean array of shape"):
        jl.fit(
            PENDULUM,
            {"g": 11.0},
            jl.Experiment(TS, data, Q0, QD0),
            args={"m": 1.0, "l": 0.8},
            estimate_initial_state=(jnp.array([True]), jnp.array([0.0])),
        )


def test_multi_start_picks_the_best_and_reports_all():
    sigma = 0.01
    rng = np.random.default_rng(0)
    clean = np.asarray(jax.vmap(lambda q: bob(q, None, TRUE))(jnp.asarray(THETA)))
    data = clean + sigma * rng.standard_normal(clean.shape)
    experiment = jl.Experiment(TS, data, Q0, QD0)
    options = dict(observe=bob, args={"m": 1.0}, noise_std=sigma)
    # A start far off ends at a local minimum: the fit says so.
    bad, messages = fit_recording(PENDULUM, {"g": 2.0, "l": 2.0}, experiment, **options)
    assert bad.reduced_chi2 is not None and bad.reduced_chi2 > 1 + 5 * np.sqrt(2 / 40)
    assert any("local minimum" in m for m in messages)
    result, messages = fit_recording(
        PENDULUM, jl.MultiStart({"g": [2.0, 11.0], "l": [2.0, 0.7]}), experiment, **options
    )
    assert messages == []
    assert result.start_losses is not None and result.start_params is not None
    np.testing.assert_allclose(result.start_losses[0], bad.loss_history[-1], rtol=1e-12)
    assert result.start_losses[1] == result.loss_history[-1] < result.start_losses[0]
    assert result.start_params["g"].shape == (2,)
    assert abs(result.params["g"] - 9.81) < 5 * result.standard_errors["g"]
    with pytest.raises(ValueError, match="same leading axis"):
        jl.MultiStart({"g": [2.0, 11.0], "l": [2.0]})


def test_multi_start_refuses_no_starts_and_mismatched_lengths():
    # Before: jl.fit(..., jl.MultiStart({"g": np.zeros(0), "l": np.zeros(0)}), ...) failed in
    # numpy with "attempt to get argmin of an empty sequence".
    experiment = jl.Experiment(TS, THETA, Q0, QD0)
    with pytest.raises(ValueError, match=r"MultiStart has zero starting points.*\(g, l\)"):
        jl.fit(PENDULUM, jl.MultiStart({"g": np.zeros(0), "l": np.zeros(0)}), experiment, args={"m": 1.0})
    with pytest.raises(ValueError, match=r"same leading axis.*got leading sizes g: 2, l: 1"):
        jl.MultiStart({"g": [2.0, 11.0], "l": [2.0]})
    with pytest.raises(ValueError, match=r"every parameter with a leading axis.*l is a scalar"):
        jl.MultiStart({"g": [2.0, 11.0], "l": 0.7})
    with pytest.raises(ValueError, match="at least one parameter"):
        jl.MultiStart({})
    # Built inside jit (shapes are static there): the same checks, at trace time.
    with pytest.raises(ValueError, match="zero starting points"):
        jax.jit(lambda g: jl.MultiStart({"g": g}).count)(jnp.zeros(0))
    assert jl.MultiStart({"g": [2.0, 11.0], "l": [2.0, 0.7]}).count == 2


def test_reversed_or_equal_bounds_are_refused_when_constructed():
    # Before: jl.Bounded(15.0, 5.0) was accepted, and a fit from g = 10 said the start "is
    # outside the domain the open interval (15.0, 5.0)".
    with pytest.raises(
        ValueError,
        match=r"Bounded\(lower=15.0, upper=5.0\): the lower bound must be below the upper bound.*"
        r"did you mean Bounded\(5.0, 15.0\)\?",
    ):
        jl.Bounded(15.0, 5.0)
    with pytest.raises(ValueError, match=r"Bounded\(lower=5.0, upper=5.0\): the lower bound must be below"):
        jl.Bounded(5.0, 5.0)
    with pytest.raises(ValueError, match=r"both bounds must be finite.*jl.Positive\(\)"):
        jl.Bounded(0.0, np.inf)
    # Inside jit, Python bounds are known: refused at trace time; traced bounds are not checked.
    with pytest.raises(ValueError, match=r"Bounded\(lower=15.0, upper=5.0\)"):
        jax.jit(lambda u: jl.Bounded(15.0, 5.0).to_physical(u))(0.0)
    mid = jax.jit(lambda lower, u: jl.Bounded(lower, 5.0).to_physical(u))(1.0, 0.0)
    assert float(mid) == 3.0
    assert float(jax.vmap(lambda u: jl.Bounded(1.0, 5.0).to_physical(u))(jnp.zeros(3))[0]) == 3.0


def test_print_fit_result_is_a_readable_summary():
    # Before: print(result) showed equinox's repr, with f64[] in place of every number.
    sigma = 0.01
    rng = np.random.default_rng(0)
    clean = np.asarray(jax.vmap(lambda q: bob(q, None, TRUE))(jnp.asarray(THETA)))
    data = clean + sigma * rng.standard_normal(clean.shape)
    result, messages = fit_recording(
        PENDULUM,
        {"g": 11.0, "l": 0.7},
        jl.Experiment(TS, data, Q0, QD0),
        observe=bob,
        args={"m": 1.0},
        noise_std=sigma,
    )
    text = str(result)
    assert text == result.summary() and "f64[" not in text
    assert repr(result).startswith("FitResult(")  # repr stays equinox's
    lines = text.splitlines()
    assert lines[0] == f"jl.fit: converged in {result.num_steps} steps; loss ½Σr² " + (
        f"{result.loss_history[0]:.4g} → {result.loss_history[-1]:.4g}"
    )
    assert "  40 degrees of freedom (finite observations − free scalars)" in lines
    chi2 = f"χ² = {result.chi2:.4g}, reduced χ² = {result.reduced_chi2:.4g} (noise_std 0.01)"
    assert any(chi2 in line for line in lines)
    for name in ("g", "l"):
        value, error = float(result.params[name]), float(result.standard_errors[name])
        row = next(line for line in lines if line.startswith(f"  {name}  "))
        shown, shown_error = row.split()[1], row.split()[3]
        assert abs(float(shown) - value) < 0.05 * error and float(shown_error) == float(f"{error:.2g}")
    rho = float(np.asarray(result.correlation)[0, 1])
    assert f"  ρ(g, l) = {rho:+.3f}" in lines
    assert "Warnings:" not in text and messages == []
    assert result.summary(min_correlation=1.0).count("ρ(") == 0
    # An undetermined fit says so in the summary, with the combination the data determine.
    angle = str(
        fit_recording(PENDULUM, {"g": 11.0, "l": 0.7}, jl.Experiment(TS, THETA, Q0, QD0), args={"m": 1.0})[0]
    )
    assert "± inf   (not determined by the data)" in angle
    assert "  g^1 · l^-1  12.2625" in angle
    assert "Warnings:\n  - only g/l is determined by the data" in angle


def test_identifiable_combination_is_the_small_angle_frequency_squared():
    """θ alone determines only g/l: the fit reports the monomial g^1 · l^-1 with its value and
    standard error, which match the closed form of a small oscillation θ0 cos(ω t), ω² = g/l:
    with known noise σ, ``SE(ω) = σ / √(Σ_i (θ0 t_i sin ω t_i)²)`` and ``SE(ω²) = 2 ω SE(ω)``."""
    theta0, omega, sigma = 1e-3, np.sqrt(9.81 / 0.8), 1e-5
    ts = np.linspace(0.0, 4.0, 41)
    clean = theta0 * np.cos(omega * ts)[:, None]
    start = {"g": 11.0, "l": 0.7}
    q0 = jnp.array([theta0])
    # Noise-free: the value is ω² up to the pendulum's amplitude correction (θ0²/8 ≈ 1.3e-7).
    exact, messages = fit_recording(PENDULUM, start, jl.Experiment(ts, clean, q0, QD0), args={"m": 1.0})
    (combination,) = exact.identifiable
    assert combination.name == "g^1 · l^-1" and combination.exponents == {"g": 1.0, "l": -1.0}
    assert abs(combination.value / omega**2 - 1) < 1e-6
    np.testing.assert_allclose(combination.value, exact.params["g"] / exact.params["l"], rtol=1e-14)
    assert exact.undetermined == ("g", "l") and len(messages) == 1
    # Noisy, noise_std known: the standard error is the closed form's.
    noisy = clean + sigma * np.random.default_rng(3).standard_normal(clean.shape)
    result, _ = fit_recording(
        PENDULUM, start, jl.Experiment(ts, noisy, q0, QD0), args={"m": 1.0}, noise_std=sigma
    )
    (combination,) = result.identifiable
    fitted = np.sqrt(combination.value)
    se_omega = sigma / np.sqrt(np.sum((theta0 * ts * np.sin(fitted * ts)) ** 2))
    np.testing.assert_allclose(combination.standard_error, 2 * fitted * se_omega, rtol=1e-3)
    assert abs(combination.value - omega**2) < 4 * combination.standard_error
    # An identifiable fit has no such combination.
    assert (
        jl.fit(
            PENDULUM, {"g": 11.0}, jl.Experiment(ts, noisy, q0, QD0), args={"m": 1.0, "l": 0.8}
        ).identifiable
        == ()
    )


def test_gross_outlier_is_named():
    # Before: one observation of 1e6 drove the fit to g = l = 0, where it failed with "M is
    # singular there" and no word about the outlier; or the fit ended at g = -269 with no warning.
    rng = np.random.default_rng(0)
    clean = np.asarray(jax.vmap(lambda q: bob(q, None, TRUE))(jnp.asarray(THETA)))
    data = clean + 0.01 * rng.standard_normal(clean.shape)
    data[7, 0] = 1e6
    where = r"experiment 0, observations\[7, 0\] = 1e\+06 at t = 0.7"
    with pytest.raises(
        jl.SimulationError,
        match=r"(?s)jl.fit, experiment 0, at parameters g=0.0, l=0.0: .*At the starting parameters, "
        r"the data hold a gross outlier: " + where + r".*mark it missing with NaN",
    ):
        jl.fit(
            PENDULUM,
            {"g": 11.0, "l": 0.7},
            jl.Experiment(TS, data, Q0, QD0),
            observe=bob,
            args={"m": 1.0},
            transforms={"g": jl.Positive(), "l": jl.Positive()},
        )
    theta = THETA.copy()
    theta[7, 0] = 1e6
    result, messages = fit_recording(
        PENDULUM, {"g": 11.0}, jl.Experiment(TS, theta, Q0, QD0), args={"m": 1.0, "l": 0.8}
    )
    (outlier,) = [m for m in messages if "outlier" in m]
    assert re.search("the data hold a gross outlier: " + where, outlier), outlier
    assert not any("not noise" in m for m in messages)  # the outlier explains the misfit
    # The same data without the outlier (NaN: missing): no warning.
    theta[7, 0] = np.nan
    result, messages = fit_recording(
        PENDULUM, {"g": 11.0}, jl.Experiment(TS, theta, Q0, QD0), args={"m": 1.0, "l": 0.8}
    )
    assert messages == [] and abs(result.params["g"] / 9.81 - 1) < 1e-7


def test_local_minimum_without_noise_std_is_warned():
    # Before: from a poor start, without noise_std, the fit ended converged=True at a local
    # minimum (residual std 0.46 for data noise 0.01) with no warning.
    rng = np.random.default_rng(0)
    clean = np.asarray(jax.vmap(lambda q: bob(q, None, TRUE))(jnp.asarray(THETA)))
    experiment = jl.Experiment(TS, clean + 0.01 * rng.standard_normal(clean.shape), Q0, QD0)
    bad, messages = fit_recording(PENDULUM, {"g": 2.0, "l": 2.0}, experiment, observe=bob, args={"m": 1.0})
    assert bad.converged and float(bad.residual_std) > 0.3
    (message,) = messages
    assert re.fullmatch(
        r"jl\.fit: the residuals are not noise: their RMS is \d+ times the noise level the data themselves "
        r"show \(≈ 0\.01\d*, from their differences\), and neighbouring residuals are correlated \(lag-1 "
        r"autocorrelation 0\.9\d\): the fit may have stopped at a local minimum, or the model does not "
        r"describe the data; try other starts with jl\.MultiStart, or give noise_std\.",
        message,
    ), message
    # From a good start: noise-like residuals, no warning.
    good, messages = fit_recording(PENDULUM, {"g": 11.0, "l": 0.7}, experiment, observe=bob, args={"m": 1.0})
    assert messages == [] and abs(float(good.residual_std) / 0.01 - 1) < 0.3
