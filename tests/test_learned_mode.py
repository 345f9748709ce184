"""Learned Lagrangians: ``System(mass_solve=jl.RobustSolve())``, checks without eigen-solvers,
equinox modules as ``args``, and the export of the check-free accelerations."""

import faulthandler

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxlag as jl


# ----------------------------------------------------------------------------- models
def _mlp_lagrangian(q, qd, args):
    """A plain LNN of a double pendulum: an MLP of (cos q, sin q, q̇)."""
    return args(jnp.concatenate([jnp.cos(q), jnp.sin(q), qd]))[0]


def _mlps(count, width=64, depth=2, seed=0):
    keys = jax.random.split(jax.random.PRNGKey(seed), count)
    return eqx.filter_vmap(
        lambda k: eqx.nn.MLP(6, 1, width, depth, activation=jax.nn.softplus, key=k, dtype=jnp.float64)
    )(keys)


Q = jnp.array([0.3, -0.5])
QD = jnp.array([0.2, 0.1])


def test_learned_mode_gives_nan_rows_and_a_count_on_512_random_lnns():
    mlps = _mlps(512)
    params, static = eqx.partition(mlps, eqx.is_array)
    robust = jl.System(_mlp_lagrangian, mass_solve=jl.RobustSolve())
    checked = jl.System(_mlp_lagrangian)

    @jax.jit
    def evaluate(p):
        def one(p):
            net = eqx.combine(p, static)
            return robust.accelerations(Q, QD, args=net), checked.mass_matrix(Q, QD, args=net)

        return jax.vmap(one)(p)

    qdd, mass = evaluate(params)
    failed = np.asarray(jnp.isnan(qdd).any(-1))
    count = int(failed.sum())
    print(f"learned mode: {count} of 512 random MLP Lagrangians fail at init")
    # Whole rows are NaN or none of them.
    assert np.array_equal(np.asarray(jnp.isnan(qdd).all(-1)), failed)
    assert 0 < count < 512
    # The failed members are those whose M = ∂²L/∂q̇² is not positive definite by the eager
    # criterion (eigenvalues, λ_min > 1e-12 λ_max): no 2x2 M here is near that boundary.
    eig = np.linalg.eigvalsh(np.asarray(mass))
    positive = eig[:, 0] > 1e-12 * np.abs(eig).max(-1)
    assert np.array_equal(failed, ~positive)
    # The others equal the checked solve (same Cholesky formula: equal to rounding).
    good = np.flatnonzero(~failed)[:32]
    reference = jax.jit(jax.vmap(lambda p: checked.accelerations(Q, QD, args=eqx.combine(p, static))))(
        jax.tree.map(lambda x: x[good], params)
    )
    np.testing.assert_allclose(qdd[good], reference, rtol=1e-13, atol=1e-13)


def test_gradients_of_failed_members_are_zero_not_nan():
    mlps = _mlps(16, width=8)
    params, static = eqx.partition(mlps, eqx.is_array)
    robust = jl.System(_mlp_lagrangian, mass_solve=jl.RobustSolve())
    target = jnp.array([1.0, -2.0])

    def member_loss(p):
        qdd = robust.accelerations(Q, QD, args=eqx.combine(p, static))
        failed = jnp.isnan(qdd).any()
        qdd = jnp.where(failed, 0.0, qdd)  # mask before any arithmetic (see RobustSolve)
        return jnp.where(failed, 0.0, jnp.sum((qdd - target) ** 2)), failed

    grads, failed = jax.jit(jax.vmap(jax.grad(member_loss, has_aux=True)))(params)
    failed = np.asarray(failed)
    assert 0 < failed.sum() < 16
    # Finite everywhere, exactly zero for the failed members: a batch mean of these is the
    # good members' gradient, not poisoned by 0 · NaN.
    for leaf in jax.tree.leaves(grads):
        assert np.all(np.isfinite(leaf))
        assert np.all(leaf[failed] == 0.0)
    assert np.all(np.any(grads.layers[0].weight[~failed] != 0.0, axis=(1, 2)))
    # A good member's gradient against central differences in one weight (relative step 1e-6:
    # truncation ~1e-12, round-off ~1e-10 relative; 1e-6 leaves margin).
    i = int(np.flatnonzero(~failed)[0])
    one = jax.tree.map(lambda x: x[i], params)
    w = one.layers[0].weight
    h = 1e-6

    def loss_at(delta):
        shifted = eqx.tree_at(lambda p: p.layers[0].weight, one, w.at[0, 0].add(delta))
        return float(member_loss(shifted)[0])

    fd = (loss_at(h) - loss_at(-h)) / (2 * h)
    assert grads.layers[0].weight[i, 0, 0] == pytest.approx(fd, rel=1e-6)


# ----------------------------------------------------------------------------- simulate
def _oscillator(q, qd, args):
    """``L = ½ a q̇² − ½ k q²``: ``M = a`` is indefinite for ``a < 0``."""
    return 0.5 * args["a"] * qd[0] ** 2 - 0.5 * args["k"] * q[0] ** 2


def test_simulate_in_learned_mode_fails_per_member_and_rollout_gradients_stay_finite():
    robust = jl.System(_oscillator, mass_solve=jl.RobustSolve())
    ts = jnp.linspace(0.0, 1.0, 5)
    q0, qd0 = jnp.ones((2, 1)), jnp.zeros((2, 1))

    def rollout_loss(k):
        """A rollout loss with the failed member masked out (before any arithmetic)."""
        args = {"a": jnp.array([1.0, -1.0]), "k": k}  # member 1: M = -1
        traj = jl.simulate_batch(robust, q0, qd0, ts, args=args, args_axes={"a": 0, "k": None}, throw=False)
        ok = traj.failure.code == jl.FailureCode.COMPLETED
        q = jnp.where(ok[:, None], traj.q[:, :, 0], 0.0)
        return jnp.sum(q[:, -1]), (traj.failure.code, q)

    (value, (code, q)), grad = jax.value_and_grad(rollout_loss, has_aux=True)(1.0)
    np.testing.assert_array_equal(code, [jl.FailureCode.COMPLETED, jl.FailureCode.NONFINITE])
    # The good member is q = cos(√k t) (default rtol = atol = 1e-10: error ≲ 1e-8), and the
    # gradient in the shared k is its own, d cos(√k t)/dk = −t sin(√k t) / (2√k) at t = 1, k = 1:
    # the failed member adds 0, not 0 · inf = NaN.
    np.testing.assert_allclose(q[0], np.cos(ts), atol=1e-8)
    assert float(grad) == pytest.approx(-np.sin(1.0) / 2.0, abs=1e-7)
    # One member alone: a failure code instead of an initial-state error.
    single = jl.simulate(robust, q0[1], qd0[1], ts, args={"a": -1.0, "k": 1.0}, throw=False)
    assert int(single.failure.code) == jl.FailureCode.NONFINITE
    # Default mode: the initial-state check raises, with the eigenvalues, as before.
    with pytest.raises(ValueError, match=r"singular or not positive definite .*eigenvalues \[-1\.\]"):
        jl.simulate(jl.System(_oscillator), q0[1], qd0[1], ts, args={"a": -1.0, "k": 1.0})


def test_rollout_stops_where_the_learned_mass_matrix_fails():
    """``M = diag(1, cos q₀)`` is positive definite for |q₀| < π/2 only: the rollout runs there
    and ends with a failure code (not an error) when q₀ = t reaches π/2."""

    def lagrangian(q, qd):
        return 0.5 * qd[0] ** 2 + 0.5 * jnp.cos(q[0]) * qd[1] ** 2

    robust = jl.System(lagrangian, mass_solve=jl.RobustSolve())
    ts = jnp.linspace(0.0, 2.0, 9)
    traj = jl.simulate(robust, jnp.zeros(2), jnp.array([1.0, 0.0]), ts, throw=False)
    assert int(traj.failure.code) != jl.FailureCode.COMPLETED
    assert 1.5 < float(traj.failure.t) <= np.pi / 2 + 1e-6
    reached = ts < 1.5
    np.testing.assert_allclose(traj.q[reached, 0], ts[reached], atol=1e-8)


def test_robust_solve_tolerance_is_a_real_number_in_0_1():
    # NumPy scalars (a float32 from a config, a 0-d array) are real numbers like any other.
    assert jl.RobustSolve(rtol=np.float32(0.5)).rtol == 0.5
    assert jl.RobustSolve(rtol=np.array(1e-9)).rtol == 1e-9
    assert jl.RobustSolve().floor(np.dtype(np.float64)) == 1e-12
    for bad in (True, 1.0, -1e-3, "1e-9", np.ones(2)):
        with pytest.raises(ValueError, match=r"real number in \[0, 1\)"):
            jl.RobustSolve(rtol=bad)


# ----------------------------------------------------------------------------- checks
def _factored_lagrangian(q, qd, args):
    """``½ q̇ᵀ C Cᵀ q̇ − ½|q|²`` with ``C = [[10⁻³, 0], [c cos q₁, 10⁻³]]``: the Cholesky pivots
    of ``M = C Cᵀ`` are ``10⁻⁶`` whatever ``c`` is, while ``κ(M) ≈ (c / 10⁻⁶)²``."""
    factor = jnp.array([[1e-3, 0.0], [args * jnp.cos(q[1]), 1e-3]])
    return 0.5 * qd @ (factor @ factor.T) @ qd - 0.5 * q @ q


def test_compiled_mass_check_sees_an_ill_conditioned_matrix_with_good_pivots():
    # c = 30: κ(M) = 8e17, singular to working precision, but every pivot is 1e-6 against
    # max M_ii = 900 (ratio 1e-9 > 1e-12). The eager check (eigenvalues) refused it; the compiled
    # pivot check let it through and the run ended at max_steps. Both now refuse it, and the
    # learned mode fails the state; c = 1e-3 (κ = 2.6) passes all three.
    q0, qd0, ts = jnp.array([0.1, 0.0]), jnp.zeros(2), jnp.linspace(0.0, 1.0, 3)
    checked = jl.System(_factored_lagrangian)
    robust = jl.System(_factored_lagrangian, mass_solve=jl.RobustSolve())
    run = jax.jit(lambda c: jl.simulate(checked, q0, qd0, ts, args=c).q)
    message = r"mass matrix M = ∂²L/∂q̇² is singular or not positive definite"
    with pytest.raises(ValueError, match=message):
        jl.simulate(checked, q0, qd0, ts, args=30.0)
    with pytest.raises(Exception, match=message):
        run(30.0)
    assert np.all(np.isnan(robust.accelerations(q0, qd0, args=30.0)))
    assert np.all(np.isfinite(run(1e-3)))
    np.testing.assert_allclose(
        robust.accelerations(q0, qd0, args=1e-3), checked.accelerations(q0, qd0, args=1e-3), rtol=1e-14
    )


def test_compiled_checks_need_no_eigen_decomposition():
    """Inside a program the definiteness and rank checks are Cholesky pivots: no LAPACK
    eigen-solver or SVD (whose batched kernels deadlocked jaxlib's CPU pool), same messages."""
    system = jl.System(_oscillator)
    program = jax.jit(lambda a: system.accelerations(jnp.ones(1), jnp.zeros(1), args={"a": a, "k": 1.0}))
    text = program.lower(1.0).as_text()
    assert "syevd" not in text and "gesdd" not in text and "potrf" not in text
    with pytest.raises(Exception, match="singular or not positive definite"):
        program(-1.0).block_until_ready()

    def twice(q):  # a pendulum constraint given twice: redundant
        return jnp.array([q @ q - 1.0, q @ q - 1.0])

    pendulum = jl.System(lambda q, qd: 0.5 * qd @ qd - 9.81 * q[1], holonomic=twice)
    state = (jnp.array([0.0, -1.0]), jnp.array([1.0, 0.0]))
    with pytest.raises(Exception, match="redundant or conflicting"):
        jax.jit(pendulum.accelerations)(*state).block_until_ready()
    with pytest.raises(ValueError, match=r"redundant or conflicting.*dependent rows: holonomic\[1\]"):
        pendulum.accelerations(*state)


def _rods(q):
    x1, y1, x2, y2 = q
    return jnp.array([x1**2 + y1**2 - 1.0, (x2 - x1) ** 2 + (y2 - y1) ** 2 - 1.0])


def _clnn(q, qd, args):
    """A constrained LNN in Cartesian coordinates: learned masses, learned potential (MLP)."""
    m = jax.nn.softplus(args["raw_mass"])
    v1, v2 = qd[:2], qd[2:]
    return 0.5 * m[0] * (v1 @ v1) + 0.5 * m[1] * (v2 @ v2) - args["potential"](q)[0]


def _cartesian(theta, theta_dot):
    s, c = jnp.sin(theta), jnp.cos(theta)
    x = jnp.cumsum(s)
    y = -jnp.cumsum(c)
    vx = jnp.cumsum(c * theta_dot)
    vy = jnp.cumsum(s * theta_dot)
    return jnp.stack([x[0], y[0], x[1], y[1]]), jnp.stack([vx[0], vy[0], vx[1], vy[1]])


def test_constrained_lnn_trains_at_full_size_under_jit_grad_vmap():
    """The case that deadlocked (batched eigvalsh/SVD of the compiled checks under
    jit(grad(vmap)) on 3,232 states, 2 cores): a few optax steps must finish. A hang would
    stall CI: faulthandler ends the process after 5 minutes with the threads' stacks."""
    faulthandler.dump_traceback_later(300, exit=True)
    try:
        count = 3232
        theta = jax.random.uniform(jax.random.PRNGKey(0), (count, 2), minval=-2.0, maxval=2.0)
        theta_dot = jax.random.normal(jax.random.PRNGKey(1), (count, 2))
        q, qd = jax.vmap(_cartesian)(theta, theta_dot)
        system = jl.System(_clnn, holonomic=_rods)  # default mode: the compiled checks are in
        mlp = eqx.nn.MLP(
            4, 1, 16, 2, activation=jax.nn.softplus, key=jax.random.PRNGKey(2), dtype=jnp.float64
        )
        params, static = eqx.partition({"raw_mass": jnp.zeros(2), "potential": mlp}, eqx.is_array)
        truth = {"raw_mass": jnp.full(2, np.log(np.e - 1.0)), "potential": lambda x: 9.81 * (x[1:2] + x[3:4])}
        optimizer = optax.sgd(1e-3)

        @jax.jit
        def step(p, state, target):
            def loss(p):
                args = eqx.combine(p, static)
                pred = jax.vmap(lambda a, b: system.accelerations(a, b, args=args))(q, qd)
                return jnp.mean((pred - target) ** 2)

            value, grads = jax.value_and_grad(loss)(p)
            updates, state = optimizer.update(grads, state)
            return optax.apply_updates(p, updates), state, value

        target = jax.jit(jax.vmap(lambda a, b: system.accelerations(a, b, args=truth)))(q, qd)
        state = optimizer.init(params)
        losses = []
        # optax's updates promote Python scalars implicitly (not allowed by the strict dtype
        # promotion that conftest.py sets for jaxlag's own code).
        with jax.numpy_dtype_promotion("standard"):
            for _ in range(3):
                params, state, value = step(params, state, target)
                losses.append(float(value))
            # The cause is gone: no LAPACK eigen-solver, SVD or Cholesky in the program.
            text = step.lower(params, state, target).as_text()
        assert not any(kernel in text for kernel in ("syevd", "gesdd", "potrf"))
    finally:
        faulthandler.cancel_dump_traceback_later()
    assert np.all(np.isfinite(losses)) and losses[-1] < losses[0]


# ----------------------------------------------------------------------------- modules as args
def _pendulum_with_net(q, qd, args):
    return 0.5 * qd[0] ** 2 + 9.81 * jnp.cos(q[0]) + 0.1 * args["net"](q)[0]


def test_an_equinox_mlp_is_accepted_as_args_everywhere():
    # 7 parameters: jax.grad takes the forward-sensitivity path (k ≤ 10).
    net = eqx.nn.MLP(1, 1, 2, 1, activation=jax.nn.softplus, key=jax.random.PRNGKey(3), dtype=jnp.float64)
    system = jl.System(_pendulum_with_net)
    ts = jnp.linspace(0.0, 0.5, 3)
    options = dict(stepsize_controller=diffrax.ConstantStepSize(), dt0=0.01)  # smooth in the weights
    q0, qd0 = jnp.array([0.5]), jnp.array([0.0])

    def final(args, q0=q0):
        return jl.simulate(system, q0, qd0, ts, args=args, **options).q[-1, 0]

    eager = final({"net": net})
    np.testing.assert_allclose(eqx.filter_jit(final)({"net": net}), eager, rtol=1e-14)
    # simulate_batch (jax.vmap of simulate) with one net per member (args_axes=0): the
    # activation function, not an array, is shared.
    nets = eqx.filter_vmap(lambda _: net)(jnp.arange(2))
    starts = jnp.array([[0.5], [0.6]])
    batch = jl.simulate_batch(
        system, starts, jnp.zeros((2, 1)), ts, args={"net": nets}, args_axes=0, **options
    )
    np.testing.assert_allclose(batch.q[0, -1, 0], eager, rtol=1e-12)
    # Gradient in the MLP's weights against central differences in one weight (a fixed step
    # size makes the discrete solution smooth in the weights; step 1e-6: error ~1e-9 relative).
    grads = eqx.filter_grad(final)({"net": net})
    w = net.layers[0].weight
    h = 1e-6

    def at(delta):
        return float(final({"net": eqx.tree_at(lambda n: n.layers[0].weight, net, w.at[0, 0].add(delta))}))

    fd = (at(h) - at(-h)) / (2 * h)
    assert grads["net"].layers[0].weight[0, 0] == pytest.approx(fd, rel=1e-6)


# ----------------------------------------------------------------------------- export
def test_learned_mode_accelerations_export_and_round_trip():
    pytest.importorskip("flatbuffers")  # jax.export's serialization needs it
    mlp = eqx.nn.MLP(4, 1, 8, 2, activation=jax.nn.softplus, key=jax.random.PRNGKey(2), dtype=jnp.float64)
    params, static = eqx.partition({"raw_mass": jnp.zeros(2), "potential": mlp}, eqx.is_array)
    leaves, treedef = jax.tree.flatten(params)
    system = jl.System(_clnn, holonomic=_rods, mass_solve=jl.RobustSolve())

    def accelerations(q, qd, leaves):
        return system.accelerations(q, qd, args=eqx.combine(jax.tree.unflatten(treedef, leaves), static))

    q, qd = _cartesian(jnp.array([0.4, -0.3]), jnp.array([1.0, 0.5]))
    exported = jax.export.export(jax.jit(accelerations))(q, qd, leaves)
    restored = jax.export.deserialize(exported.serialize())
    np.testing.assert_allclose(
        restored.call(q, qd, leaves), accelerations(q, qd, leaves), rtol=1e-14, atol=1e-14
    )
    # The exported function keeps learned mode's NaN for a failed state, without a callback.
    bad = jax.tree.unflatten(treedef, leaves)
    bad = eqx.tree_at(lambda p: p["raw_mass"], bad, jnp.array([0.0, -1e3]))  # softplus: m₂ = 0
    assert np.all(np.isnan(restored.call(q, qd, jax.tree.leaves(bad))))
