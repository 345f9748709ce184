"""System identification: parameters recovered from simulated observations."""

import contextlib
import inspect
import warnings

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import optax
import optimistix as optx
import pytest

import jaxlag as jl

TRUE = {"g": 9.81, "l": 0.8}
START = {"g": 9.81 * 1.2, "l": 0.8 * 0.8}  # 20% off
TS = jnp.linspace(0.0, 3.0, 61)
Q0, QD0 = jnp.array([0.9]), jnp.array([0.0])


def pendulum(q, qd, args):
    return 0.5 * args["l"] ** 2 * qd[0] ** 2 + args["g"] * args["l"] * jnp.cos(q[0])


def bob(q, qd, args):
    """What a camera sees: the bob's Cartesian position l (sin θ, −cos θ)."""
    return args["l"] * jnp.array([jnp.sin(q[0]), -jnp.cos(q[0])])


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


def observe_bob(args, q0=Q0, ts=TS):
    traj = jl.simulate(PENDULUM, q0, QD0, ts, args=args)
    return jax.vmap(lambda q: bob(q, None, args))(traj.q)


def test_pendulum_g_and_l_from_noise_free_bob_positions():
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", jl.FitWarning)  # a good fit warns about nothing
        result = jl.fit(
            PENDULUM, START, experiment, observe=bob, transforms={"g": jl.Positive(), "l": jl.Positive()}
        )
    assert result.converged
    # Noise-free data and a simulation at rtol 1e-10: recovery limited by the integrator only.
    for name in TRUE:
        assert abs(result.params[name] / TRUE[name] - 1) < 1e-6
    assert result.loss_history[-1] < 1e-16 * result.loss_history[0]


def test_angle_alone_identifies_only_g_over_l():
    theta = jl.simulate(PENDULUM, Q0, QD0, TS, args=TRUE).q
    with pytest.warns(jl.FitWarning, match="only g/l is determined by the data"):
        result = jl.fit(PENDULUM, START, jl.Experiment(TS, theta, Q0, QD0))
    ratio = result.params["g"] / result.params["l"]
    assert abs(ratio / (TRUE["g"] / TRUE["l"]) - 1) < 1e-6
    # The individual values are not identified: the direction (g, l) ∝ (g, l) is flat.
    assert abs(result.params["l"] / TRUE["l"] - 1) > 1e-3


def test_noisy_estimates_are_within_three_standard_errors_for_twenty_seeds():
    # Calibration measured over seeds 0–299 (same setup): std(z) = 1.02 for g and 1.00 for l,
    # P(|z| < 2) = 0.95, P(|z| < 3) = 0.987 / 0.993 (σ is estimated, so the tails are slightly
    # heavier than normal). The fixed set is seeds 20–39; seed 5, for instance, gives |z| = 3.6.
    clean = observe_bob(TRUE)
    sigma = 0.01
    z_scores = []
    for seed in range(20, 40):
        noisy = clean + sigma * np.random.default_rng(seed).standard_normal(clean.shape)
        with warnings.catch_warnings():
            # No false alarm (outliers, residuals that are not noise) on twenty good fits.
            warnings.simplefilter("error", jl.FitWarning)
            result = jl.fit(PENDULUM, START, jl.Experiment(TS, noisy, Q0, QD0), observe=bob)
        for name in TRUE:
            z_scores.append((result.params[name] - TRUE[name]) / result.standard_errors[name])
        # The residual standard deviation estimates the noise level.
        assert abs(result.residual_std / sigma - 1) < 0.25
    z = np.abs(np.array(z_scores))
    assert np.all(z < 3.0), z
    # Standard errors are calibrated, not merely large.
    assert 0.6 < np.std(np.array(z_scores)) < 1.5
    assert np.mean(z < 2.0) > 0.8


def test_several_experiments_are_batched():
    q0s = [jnp.array([0.3]), jnp.array([0.9]), jnp.array([1.6])]
    experiments = [jl.Experiment(TS, observe_bob(TRUE, q0), q0, QD0) for q0 in q0s]
    result = jl.fit(PENDULUM, START, experiments, observe=bob)
    for name in TRUE:
        assert abs(result.params[name] / TRUE[name] - 1) < 1e-6


def test_initial_state_is_estimated_too():
    experiment = jl.Experiment(TS, observe_bob(TRUE), jnp.array([0.7]), jnp.array([0.2]))
    result = jl.fit(PENDULUM, START, experiment, observe=bob, estimate_initial_state=True)
    q0, qd0 = result.initial_states
    np.testing.assert_allclose(q0[0], Q0, atol=1e-7)
    np.testing.assert_allclose(qd0[0], QD0, atol=1e-6)
    assert abs(result.params["g"] / TRUE["g"] - 1) < 1e-6


def test_multiple_shooting_agrees_with_single_shooting():
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)
    result = jl.fit(PENDULUM, START, experiment, observe=bob, shooting=jl.Shooting(segments=4))
    for name in TRUE:
        assert abs(result.params[name] / TRUE[name] - 1) < 1e-6


def hoop(q, qd, args):
    """Bead on a vertical hoop in polar coordinates (r, θ), θ from the bottom."""
    r, th = q
    rd, thd = qd
    return 0.5 * (rd**2 + r**2 * thd**2) + args["g"] * r * jnp.cos(th)


def on_hoop(q, args):
    return jnp.array([q[0] - args["R"]])


def cartesian(q, qd):
    return q[0] * jnp.array([jnp.sin(q[1]), -jnp.cos(q[1])])


def test_hoop_radius_from_cartesian_positions_through_the_kkt_solve():
    system = jl.System(hoop, holonomic=on_hoop)
    truth = {"g": 9.81, "R": 1.3}
    q0, qd0 = jnp.array([1.3, 1.0]), jnp.array([0.0, 0.5])
    traj = jl.simulate(system, q0, qd0, TS, args=truth)
    observed = jax.vmap(lambda q: cartesian(q, None))(traj.q)
    # The starting guess R = 1.0 is inconsistent with q0: the fit projects each initial state
    # onto the manifold of the current parameters (jl.consistent_initial_state).
    result = jl.fit(
        system, {"R": 1.0}, jl.Experiment(TS, observed, q0, qd0), observe=cartesian, args={"g": 9.81}
    )
    assert abs(result.params["R"] / 1.3 - 1) < 1e-6


def test_damping_coefficient_of_an_oscillator():
    system = jl.System(
        lambda q, qd, args: 0.5 * qd[0] ** 2 - 2.0 * q[0] ** 2,
        dissipation=lambda q, qd, args: 0.5 * args["c"] * qd[0] ** 2,
    )
    traj = jl.simulate(system, jnp.array([1.0]), jnp.zeros(1), TS, args={"c": 0.35})
    result = jl.fit(
        system,
        {"c": 0.1},
        jl.Experiment(TS, traj.q, jnp.array([1.0]), jnp.zeros(1)),
        transforms={"c": jl.Positive()},
    )
    assert abs(result.params["c"] / 0.35 - 1) < 1e-6


def test_optax_path_decreases_the_loss():
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)
    # optax's adam raises an integer step count to a float power: not clean under the suite's
    # strict dtype promotion, so this test runs with JAX's default promotion (as users do).
    with jax.numpy_dtype_promotion("standard"):
        result = jl.fit(
            PENDULUM, START, experiment, observe=bob, optimizer=optax.adam(0.05), max_steps=60, progress=True
        )
    assert len(result.loss_history) == 61
    assert result.loss_history[-1] < 0.05 * result.loss_history[0]


def test_loss_gradient_matches_central_differences():
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)

    def loss(g, l):
        return jl.least_squares_loss(PENDULUM, {"g": g, "l": l}, experiment, observe=bob)

    grad = jax.grad(loss, argnums=(0, 1))(*START.values())
    forward = jax.jacfwd(
        lambda x: jl.least_squares_loss(
            PENDULUM,
            {"g": x[0], "l": x[1]},
            experiment,
            observe=bob,
            simulation=dict(adjoint=diffrax.ForwardMode()),
        )
    )(jnp.array(list(START.values())))
    h = 1e-5
    for i, name in enumerate(START):
        plus, minus = dict(START), dict(START)
        plus[name] += h
        minus[name] -= h
        fd = (loss(**plus) - loss(**minus)) / (2 * h)
        # Adaptive steps at rtol 1e-10: FD noise ~ tol·|loss|/h ≈ 1e-5·|loss| relative is the
        # floor, truncation h² is negligible.
        assert abs(grad[i] - fd) / abs(fd) < 1e-4
        # Reverse mode (RecursiveCheckpointAdjoint) and forward mode agree to round-off.
        assert abs(grad[i] - forward[i]) / abs(forward[i]) < 1e-9


def test_missing_observations_are_masked():
    observed = np.array(observe_bob(TRUE))
    observed[5:20:3, 0] = np.nan
    result = jl.fit(PENDULUM, START, jl.Experiment(TS, observed, Q0, QD0), observe=bob)
    assert abs(result.params["l"] / TRUE["l"] - 1) < 1e-6


def test_bad_input():
    observed = observe_bob(TRUE)
    with pytest.raises(ValueError, match="increasing"):
        jl.fit(PENDULUM, START, jl.Experiment(TS[::-1], observed, Q0, QD0), observe=bob)
    with pytest.raises(ValueError, match="observation function returns shape"):
        jl.fit(PENDULUM, START, jl.Experiment(TS, observed, Q0, QD0))  # observes q: shape (1,)
    with pytest.raises(ValueError, match="All observations are NaN"):
        jl.fit(PENDULUM, START, jl.Experiment(TS, jnp.full_like(observed, jnp.nan), Q0, QD0), observe=bob)
    with pytest.raises(ValueError, match="same shapes"):
        jl.fit(
            PENDULUM,
            START,
            [jl.Experiment(TS, observed, Q0, QD0), jl.Experiment(TS[:10], observed[:10], Q0, QD0)],
            observe=bob,
        )
    with pytest.raises(ValueError, match=r"Shooting\(segments=7\).*must divide"):
        jl.fit(
            PENDULUM,
            START,
            jl.Experiment(TS, observed, Q0, QD0),
            observe=bob,
            shooting=jl.Shooting(segments=7),
        )
    with pytest.raises(ValueError, match="transforms"):
        jl.fit(
            PENDULUM,
            START,
            jl.Experiment(TS, observed, Q0, QD0),
            observe=bob,
            transforms={"m": jl.Positive()},
        )


def test_failures_during_a_fit_are_raised_from_the_host():
    """The least-squares program returns its checks and the host raises them (no callback in the
    program, so JAX's persistent cache can store it): a simulation that fails at the parameters
    being tried, and an initial state the projection cannot bring onto the constraints."""
    observed = observe_bob(TRUE)
    with pytest.raises(jl.SimulationError, match=r"jl.fit, experiment 1, at parameters .*max_steps"):
        jl.fit(
            PENDULUM,
            START,
            [jl.Experiment(TS[:5], observed[:5], Q0, QD0), jl.Experiment(TS[:5] * 20, observed[:5], Q0, QD0)],
            observe=bob,
            simulation=dict(max_steps=64),
        )
    # A bead that should sit at distance l from the pivot, but the constraint |x| = −l has no
    # solution for l > 0: the projection of the initial state fails.
    bead = jl.System(
        lambda q, qd, args: 0.5 * jnp.sum(qd**2) - args["g"] * q[1],
        holonomic=lambda q, args: jnp.array([jnp.sum(q**2) + args["l"] ** 2]),
    )
    with pytest.raises(ValueError, match="jl.fit, experiment 0: consistent_initial_state"):
        jl.fit(
            bead,
            START,
            jl.Experiment(TS[:5], observed[:5], jnp.array([0.5, -0.5]), jnp.zeros(2)),
            observe=lambda q, qd: q,
        )


def test_one_experiment_path_equals_the_batched_one():
    """One experiment with one segment skips the vmaps over experiments and segments (no
    batching transform of the solver): its loss and gradient equal half those of the same
    experiment given twice (the batched path), to rounding."""
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)

    def loss(params, experiments):
        return jl.least_squares_loss(PENDULUM, params, experiments, observe=bob)

    one, grad_one = jax.value_and_grad(loss)(START, experiment)
    two, grad_two = jax.value_and_grad(loss)(START, [experiment, experiment])
    np.testing.assert_allclose(two, 2 * one, rtol=1e-13)
    for name in START:
        np.testing.assert_allclose(grad_two[name], 2 * grad_one[name], rtol=1e-11)


def test_default_optimizer_is_the_old_default():
    """``optimizer`` defaults to optimistix' Levenberg–Marquardt at rtol = atol = 1e-10 (the old
    ``method="levenberg_marquardt"``, ``rtol=1e-10``, ``atol=1e-10``): the same steps as the
    explicit solver object, and the optimum the old API found on the same data."""
    default = inspect.signature(jl.fit).parameters["optimizer"].default
    assert eqx.tree_equal(default, optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10))
    clean = observe_bob(TRUE)
    noisy = clean + 0.01 * np.random.default_rng(0).standard_normal(clean.shape)
    experiment = jl.Experiment(TS, noisy, Q0, QD0)
    positive = {"g": jl.Positive(), "l": jl.Positive()}
    implicit = jl.fit(PENDULUM, START, experiment, observe=bob, transforms=positive)
    explicit = jl.fit(
        PENDULUM,
        START,
        experiment,
        observe=bob,
        transforms=positive,
        optimizer=optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10),
    )
    assert implicit.converged and implicit.num_steps == explicit.num_steps
    np.testing.assert_array_equal(implicit.loss_history, explicit.loss_history)
    # jl.fit(..., method="levenberg_marquardt") before the option objects, same data and start.
    old = {"g": 9.798405886708514, "l": 0.7986614019022151}
    for name in TRUE:
        assert implicit.params[name] == explicit.params[name]
        assert abs(implicit.params[name] / old[name] - 1) < 1e-9


@pytest.mark.parametrize("solver", [optx.GaussNewton, optx.Dogleg, optx.IndirectLevenbergMarquardt])
def test_gauss_newton_type_solver_objects(solver):
    """Every optimistix solver of the Gauss–Newton family steps on the linearized residuals."""
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)
    result = jl.fit(PENDULUM, START, experiment, observe=bob, optimizer=solver(rtol=1e-10, atol=1e-10))
    assert result.converged
    for name in TRUE:
        assert abs(result.params[name] / TRUE[name] - 1) < 1e-6


def test_three_shooting_segments_as_before_and_periodic_segment_states():
    """``shooting=jl.Shooting(segments=3)`` finds the optimum the old ``shooting_segments=3``
    found; segment states given in another branch of a periodic coordinate
    (``periodic_coordinates``) lead to the same fit."""
    clean = observe_bob(TRUE)
    noisy = clean + 0.01 * np.random.default_rng(0).standard_normal(clean.shape)
    experiment = jl.Experiment(TS, noisy, Q0, QD0)
    positive = {"g": jl.Positive(), "l": jl.Positive()}
    result = jl.fit(
        PENDULUM, START, experiment, observe=bob, transforms=positive, shooting=jl.Shooting(segments=3)
    )
    assert result.converged
    q, qd = (np.asarray(s) for s in result.segment_states)
    assert q.shape == qd.shape == (1, 3, 1)
    # jl.fit(..., shooting_segments=3) before the option objects, same data and start.
    old = {"g": 9.798787486219824, "l": 0.7986615031047841}
    for name in TRUE:
        assert abs(result.params[name] / old[name] - 1) < 1e-9
    q = q.copy()
    q[:, 1:] += 2 * np.pi
    shifted = jl.fit(
        PENDULUM,
        START,
        experiment,
        observe=bob,
        transforms=positive,
        shooting=jl.Shooting(segments=3, states=(q, qd), periodic_coordinates=(0,)),
    )
    assert shifted.converged
    np.testing.assert_allclose(shifted.segment_states[0][:, 1:], q[:, 1:], atol=1e-6)
    for name in TRUE:
        assert abs(shifted.params[name] / result.params[name] - 1) < 1e-9


def test_bad_option_objects():
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)
    with without_type_checks():
        with pytest.raises(TypeError, match=r"not the string 'gauss_newton'.*optx\.GaussNewton\(rtol=1e-10"):
            jl.fit(PENDULUM, START, experiment, observe=bob, optimizer="gauss_newton")
        with pytest.raises(TypeError, match="Gauss–Newton-type solver.*got BestSoFarLeastSquares"):
            jl.fit(
                PENDULUM,
                START,
                experiment,
                observe=bob,
                optimizer=optx.BestSoFarLeastSquares(optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)),
            )
        with pytest.raises(TypeError, match="optax.GradientTransformation.*got BFGS"):
            jl.fit(PENDULUM, START, experiment, observe=bob, optimizer=optx.BFGS(rtol=1e-8, atol=1e-8))
        with pytest.raises(TypeError, match="method"):
            jl.fit(PENDULUM, START, experiment, observe=bob, method="gauss_newton")
        with pytest.raises(ValueError, match=r"Shooting\(segments=0\).*at least 1"):
            jl.Shooting(segments=0)
        with pytest.raises(TypeError, match=r"Shooting\(segments=\.\.\.\) must be an int"):
            jl.Shooting(segments=2.0)
        with pytest.raises(ValueError, match=r"continuity_weight=0\.0.*must be positive"):
            jl.Shooting(continuity_weight=0.0)
        with pytest.raises(TypeError, match=r"shooting must be a jl\.Shooting"):
            jl.fit(PENDULUM, START, experiment, observe=bob, shooting=3)
        with pytest.raises(ValueError, match=r"Shooting\(states=\(q, qd\)\) must have shape \(1, 3, 1\)"):
            jl.fit(
                PENDULUM,
                START,
                experiment,
                observe=bob,
                shooting=jl.Shooting(segments=3, states=(np.zeros((1, 2, 1)), np.zeros((1, 2, 1)))),
            )


def test_simulation_options_are_one_object_forwarded_to_simulate():
    """``simulation=`` takes jl.simulate's options as one dict (a jl.SimulateOptions), forwarded
    untouched; the fit's own ``max_steps`` stays the optimizer's; MultiStart forwards the same
    object. Before: six keywords of their own (``max_solver_steps`` for simulate's max_steps)."""
    parameters = inspect.signature(jl.fit).parameters
    named = [p for p in parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    assert len(named) == 13 and "simulation" in parameters and "solver" not in parameters
    assert parameters["simulation"].default == {}  # simulate's own defaults
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)
    options = jl.SimulateOptions(solver=diffrax.Dopri8(), max_steps=4096)
    result = jl.fit(PENDULUM, START, experiment, observe=bob, simulation=options, max_steps=30)
    assert result.converged and abs(result.params["g"] / TRUE["g"] - 1) < 1e-6
    # Simulate's max_steps reaches every simulation, of every start of a MultiStart.
    short = [jl.Experiment(TS[:5] * 20, observe_bob(TRUE)[:5], Q0, QD0)]
    with pytest.raises(jl.SimulationError, match=r"experiment 0, at parameters .*max_steps"):
        jl.fit(PENDULUM, START, short, observe=bob, simulation=dict(max_steps=64))
    starts = jl.MultiStart({"g": [11.0, 9.0], "l": [0.7, 0.9]})
    with pytest.raises(ValueError, match=r"MultiStart: every one of the 2 fits failed.*max_steps"):
        jl.fit(PENDULUM, starts, short, observe=bob, simulation=dict(max_steps=64))
    # Names are checked; options the fit sets itself are refused with the reason.
    with pytest.raises(
        TypeError,
        match=r"jl.fit\(simulation=...\): simulate\(\) got an unexpected keyword "
        r"argument 'max_solver_steps'",
    ):
        jl.fit(PENDULUM, START, experiment, observe=bob, simulation=dict(max_solver_steps=64))
    with pytest.raises(
        ValueError,
        match=r"sets 'saveat', 'throw' itself: saveat: the simulation saves at "
        r"each experiment's save times ts.*; throw: the fit raises a failed simulation itself",
    ):
        jl.fit(
            PENDULUM,
            START,
            experiment,
            observe=bob,
            simulation=dict(saveat=diffrax.SaveAt(t1=True), throw=False),
        )
    with pytest.raises(ValueError, match=r"'adjoint' itself: adjoint: the fit differentiates the simulation"):
        jl.fit(PENDULUM, START, experiment, observe=bob, simulation=dict(adjoint=diffrax.ForwardMode()))


def test_old_simulation_keywords_are_deprecated_and_give_the_same_fit():
    experiment = jl.Experiment(TS, observe_bob(TRUE), Q0, QD0)
    new = jl.fit(
        PENDULUM, START, experiment, observe=bob, simulation=dict(solver=diffrax.Dopri8(), max_steps=4096)
    )
    with pytest.warns(DeprecationWarning) as caught:
        old = jl.fit(PENDULUM, START, experiment, observe=bob, solver=diffrax.Dopri8(), max_solver_steps=4096)
    assert [str(w.message) for w in caught] == [
        "jl.fit(solver=...) is deprecated and will be removed in the next release: pass "
        "simulation=dict(solver=...) (the options of jl.simulate, forwarded to it untouched).",
        "jl.fit(max_solver_steps=...) is deprecated and will be removed in the next release: pass "
        "simulation=dict(max_steps=...) (the options of jl.simulate, forwarded to it untouched).",
    ]
    np.testing.assert_array_equal(old.loss_history, new.loss_history)
    with pytest.raises(
        TypeError, match=r"max_solver_steps= and simulation=\{'max_steps': ...\} give the same"
    ):
        jl.fit(PENDULUM, START, experiment, observe=bob, max_solver_steps=64, simulation=dict(max_steps=64))
    with pytest.warns(
        DeprecationWarning,
        match=r"least_squares_loss\(adjoint=...\) is deprecated.*"
        r"simulation=dict\(adjoint=...\)",
    ):
        loss = jl.least_squares_loss(PENDULUM, START, experiment, observe=bob, adjoint=diffrax.ForwardMode())
    np.testing.assert_allclose(
        loss, jl.least_squares_loss(PENDULUM, START, experiment, observe=bob), rtol=1e-12
    )
