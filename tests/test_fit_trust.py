"""jl.fit reports what the data cannot determine, how well it fits, and refuses bad input."""

import warnings

import jax
import jax.numpy as jnp
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
    with pytest.raises(ValueError, match=r"qd_mask must be a boolean array of shape \(1,\)"):
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
