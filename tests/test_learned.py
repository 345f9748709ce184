"""jaxlag.learned: structured Lagrangians, NaN-masked losses, rollout gradients and the train loop."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

import jaxlag as jl
from jaxlag import learned as jll

KEY = jax.random.PRNGKey(0)


# ---------------------------------------------------------------------------- models
_delan_mass = eqx.filter_jit(
    lambda model, q: (
        model.factor(q),
        model.mass_matrix(q),
        jax.hessian(model, argnums=1)(q, q),
        jll.accelerations(model, q, q),
    )
)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), weight_scale=st.sampled_from([0.1, 1.0, 10.0]))
@example(seed=280779, weight_scale=10.0)  # κ(C) = 6e13: its pivots C_jj² pass, κ̂ does not
@example(seed=2, weight_scale=10.0)  # κ(C)² = 1.5e18
def test_delan_mass_matrix_is_positive_definite(seed, weight_scale):
    # Random weights (scaled up to make the factor's entries large and of either sign) and random
    # states. M = C Cᵀ with C lower triangular and diag(C) ≥ floor: SPD in exact arithmetic, and
    # it is ∂²L/∂q̇². In floating point κ(M) = κ(C)²: a well-conditioned M factors and gives finite
    # accelerations; one singular to working precision (seen: κ(C) = 6e13 at weight scale 10)
    # fails that state in learned mode, NaN, never a wrong q̈.
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    model = jll.DeLaN(3, 8, 1, key=k1, embedding=jll.AngleEmbedding((0, 2)))
    model = jax.tree.map(lambda x: x * weight_scale if eqx.is_inexact_array(x) else x, model)
    q = 3.0 * jax.random.normal(k2, (3,))
    factor, mass, hessian, qdd = (np.asarray(x) for x in _delan_mass(model, q))
    assert np.all(np.triu(factor, 1) == 0) and np.all(np.diag(factor) >= model.floor)
    np.testing.assert_allclose(hessian, mass, rtol=1e-12, atol=1e-12 * float(np.max(np.abs(mass))))
    condition = np.linalg.cond(factor) ** 2
    # RobustSolve passes every M with κ ≤ 1e12 and fails every M with κ > n² · 1e12 = 9e12.
    if condition < 1e10:
        assert np.all(np.isfinite(np.linalg.cholesky(mass)))
        assert np.all(np.isfinite(qdd))
    elif condition > 1e14:
        assert np.all(np.isnan(qdd))


def test_angle_embedding_and_bad_input():
    emb = jll.AngleEmbedding((1,))
    np.testing.assert_allclose(emb(jnp.array([0.5, jnp.pi / 2, 2.0])), [0.0, 1.0, 0.5, 2.0], atol=1e-15)
    with pytest.raises(ValueError, match="out of range"):
        jll.MLPLagrangian(1, 4, 1, key=KEY, embedding=jll.AngleEmbedding((1,)))
    with pytest.raises(ValueError, match="distinct"):
        jll.AngleEmbedding((0, 0))
    # The suite's run-time type checker refuses the mismatched n from the annotations (a
    # TypeError); without it, as users run, StateData's own check does (a ValueError).
    with pytest.raises((ValueError, TypeError), match="qdd"):
        jll.StateData(jnp.zeros((3, 2)), jnp.zeros((3, 2)), jnp.zeros((3, 1)))


def test_indefinite_members_are_nan_and_counted_not_averaged():
    # A plain LNN at initialization: its Hessian in q̇ is indefinite at most states (issue 29:
    # 495 of 512). Those members are NaN and counted; the mean and its gradient stay finite.
    key = jax.random.PRNGKey(1)  # a draw whose batch mixes definite and indefinite states (28 of 64)
    model = jll.MLPLagrangian(2, 16, 2, key=key, positive_output_init=False)
    keys = jax.random.split(key, 3)
    data = jll.StateData(*(jax.random.normal(k, (64, 2)) for k in keys))

    @eqx.filter_jit
    def evaluate(m):
        def objective(m):
            out = jll.AccelerationLoss()(m, data)
            return out.value, out

        out, grads = eqx.filter_value_and_grad(objective, has_aux=True)(m)
        qdd = jax.vmap(lambda q, qd: jll.accelerations(m, q, qd))(data.q, data.qd)
        return out, grads, qdd

    (value, out), grads, qdd = evaluate(model)
    bad = ~np.all(np.isfinite(np.asarray(qdd)), axis=1)
    assert 0 < bad.sum() < 64 and int(out.failed) == bad.sum()
    assert np.all(np.isnan(np.asarray(qdd)[bad]))  # the whole vector of a failed state
    assert np.isfinite(float(value))
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(eqx.filter(grads, eqx.is_inexact_array)))


# ---------------------------------------------------------------------------- identification
def test_delan_recovers_pendulum_mass_and_potential():
    # Simple pendulum m = 2, l = 0.5: M = m l² = 0.5, V(θ) − V(0) = m g l (1 − cos θ), g = 9.81.
    # Known applied torques fix the scale of L (from (q, q̇, q̈) alone L and cL move alike).
    m, l, g = 2.0, 0.5, 9.81
    k1, k2, k3, k4 = jax.random.split(KEY, 4)
    q = jax.random.uniform(k1, (256, 1), minval=-jnp.pi, maxval=jnp.pi)
    qd = jax.random.uniform(k2, (256, 1), minval=-3.0, maxval=3.0)
    torque = jax.random.uniform(k3, (256, 1), minval=-2.0, maxval=2.0)
    qdd = (torque - m * g * l * jnp.sin(q)) / (m * l**2)
    data = jll.StateData(q, qd, qdd, forces=torque)
    model = jll.DeLaN(1, 32, 1, key=k4, embedding=jll.AngleEmbedding(0))
    schedule = optax.warmup_cosine_decay_schedule(0.0, 3e-2, 50, 800, 3e-4)
    with jax.numpy_dtype_promotion("standard"):  # optax mixes int32 step counts with floats
        result = jll.train(model, jll.AccelerationLoss(), data, optimizer=optax.adam(schedule), steps=800)
    fitted = result.model
    grid = jnp.linspace(-jnp.pi, jnp.pi, 41)[:, None]
    mass = jax.vmap(fitted.mass_matrix)(grid)[:, 0, 0]
    potential = jax.vmap(fitted.potential)(grid)
    potential = potential - fitted.potential(jnp.zeros(1))
    truth = m * g * l * (1.0 - jnp.cos(grid[:, 0]))
    # Tolerances: 800 adam steps on exact, noise-free data leave a mean squared acceleration
    # error of ~1e-3 (rad/s²)² against accelerations of ~20 rad/s², the MLP's approximation
    # error; measured: M within 1.5 % and V within 0.6 % of its range 2 m g l at every angle of
    # the grid. 3 % and 2 % leave room for other BLAS and rounding, not for a wrong model.
    np.testing.assert_allclose(mass, m * l**2, rtol=0.03)
    assert float(jnp.max(jnp.abs(potential - truth))) < 0.02 * 2 * m * g * l


# ---------------------------------------------------------------------------- rollouts
def test_rollout_loss_gradient_matches_finite_differences():
    model = jll.DeLaN(1, 4, 1, key=KEY, embedding=jll.AngleEmbedding(0))
    ts = jnp.linspace(0.0, 0.5, 6)
    q = jnp.stack([0.5 * jnp.cos(3.0 * ts), -0.3 * jnp.cos(3.0 * ts)])[..., None]
    qd = jnp.stack([-1.5 * jnp.sin(3.0 * ts), 0.9 * jnp.sin(3.0 * ts)])[..., None]
    data = jll.TrajectoryData(jnp.broadcast_to(ts, (2, 6)), q, qd)
    loss = jll.RolloutLoss(substeps=2, velocities=True)
    params, static = eqx.partition(model, eqx.is_inexact_array)
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    def value(x):
        return loss(eqx.combine(unravel(x), static), data).value

    value_and_grad = jax.jit(jax.value_and_grad(value))  # one program for the gradient and the FD values
    _, grad = value_and_grad(flat)
    h = 1e-5
    # The factor's first weight, one in the middle, the potential's last weight (its bias, the
    # last entry, does not change the motion: zero gradient).
    for i in (0, flat.shape[0] // 2, flat.shape[0] - 2):
        e = jnp.zeros_like(flat).at[i].set(h)
        fd = (value_and_grad(flat + e)[0] - value_and_grad(flat - e)[0]) / (2 * h)
        # Central differences: truncation ~h²·|f'''| ~ 1e-10 and round-off ~ε|f|/h ~ 1e-11 against
        # derivatives of order 1e-2..1e-1 (measured: relative differences 3e-11..2e-10); 1e-6
        # relative bounds the FD error, not the gradient's.
        np.testing.assert_allclose(grad[i], fd, rtol=1e-6, atol=1e-9)


class _SofteningSpring(jll.AbstractLagrangian):
    """``L = ½(1 − a q²) q̇² − ½ k q²``: its mass ``1 − a q²`` turns negative beyond ``|q| = 1/√a``."""

    a: jax.Array
    k: jax.Array

    def __call__(self, q, qd):
        return 0.5 * (1.0 - self.a * q[0] ** 2) * qd[0] ** 2 - 0.5 * self.k * q[0] ** 2


def test_member_failing_mid_rollout_leaves_the_gradient_of_the_others():
    # Oscillations of the unit oscillator; the model's mass 1 − 0.3q² fails past |q| = 1.83, which
    # only the last member (q̇0 = 2.4: amplitude about 2) reaches, after a few steps. Masking its
    # outputs alone gave a NaN gradient (0 · NaN in the backward pass of its steps after the
    # failure); the loss must give exactly the gradient of the three members that finish.
    ts = jnp.linspace(0.0, 3.0, 31)
    q0 = jnp.array([[0.5], [1.0], [-1.2], [0.0]])
    qd0 = jnp.array([[0.0], [0.5], [0.0], [2.4]])
    truth = jl.simulate_batch(jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2), q0, qd0, ts)
    data = jll.TrajectoryData(jnp.broadcast_to(ts, (4, 31)), truth.q, truth.qd)
    loss = jll.RolloutLoss()

    def value(theta, data):
        return loss(_SofteningSpring(theta[0], theta[1]), data)

    grad = jax.jit(jax.value_and_grad(lambda th, d: value(th, d).value))
    theta = jnp.array([0.3, 1.1])
    assert int(value(theta, data).failed) == 1
    rollout_q, _, ok = loss.rollout(_SofteningSpring(theta[0], theta[1]), data)
    assert not bool(ok[3]) and int(jnp.sum(jnp.isfinite(rollout_q[3]))) > 3  # fails mid-way
    loss_value, g = grad(theta, data)
    finished = jll.TrajectoryData(data.ts[:3], data.q[:3], data.qd[:3])
    loss_three, g_three = grad(theta, finished)
    assert np.all(np.isfinite(g))
    # The same discrete computation on the same three members: equal to round-off.
    np.testing.assert_allclose(loss_value, loss_three, rtol=1e-14)
    np.testing.assert_allclose(g, g_three, rtol=1e-12)
    h = 1e-6
    for i in range(2):
        e = jnp.zeros(2).at[i].set(h)
        fd = (grad(theta + e, data)[0] - grad(theta - e, data)[0]) / (2 * h)
        # Central differences of an O(1) loss: truncation h²|f'''| ~ 1e-12, round-off ε/h ~ 1e-10.
        np.testing.assert_allclose(g[i], fd, rtol=1e-7)


def test_constrained_lnn_keeps_the_constraint():
    # Cartesian pendulum: one body in 2-D on a rod of length 1.2; untrained learned masses and
    # potential. The KKT solve gives J ẍ = −γ exactly (round-off) and the rollout, projected
    # after every step by jl.Projection(), keeps |f| at round-off.
    def rod(x):
        return jnp.array([jnp.sqrt(x @ x) - 1.2])

    model = jll.ConstrainedLagrangian(1, 2, rod, 8, 1, key=KEY)
    x0 = 1.2 * jnp.array([jnp.sin(0.7), -jnp.cos(0.7)])
    xd0 = 2.0 * jnp.array([jnp.cos(0.7), jnp.sin(0.7)])
    xdd = jll.accelerations(model, x0, xd0)
    jac = jax.jacfwd(rod)(x0)
    gamma = jax.jvp(lambda s: jax.jvp(rod, (x0 + s * xd0,), (xd0,))[1], (0.0,), (1.0,))[1]
    np.testing.assert_allclose(jac @ xdd, -gamma, atol=1e-12)
    traj = jl.simulate(model.system(), x0, xd0, jnp.linspace(0.0, 3.0, 31))
    residual = jax.vmap(rod)(traj.q)
    velocity_residual = jax.vmap(lambda x, v: jax.jacfwd(rod)(x) @ v)(traj.q, traj.qd)
    # The projection's Newton steps leave |f| and |J ẋ| at round-off of lengths ~1 (1e-15); 1e-12
    # allows for the accumulated rounding of 3 s of steps.
    assert float(jnp.max(jnp.abs(residual))) < 1e-12
    assert float(jnp.max(jnp.abs(velocity_residual))) < 1e-12


# ---------------------------------------------------------------------------- training
class _Scalar(eqx.Module):
    w: jax.Array


def _quadratic(model, data):
    return jll.LossValue(jnp.mean((model.w - data) ** 2), jnp.zeros((), jnp.int32))


def test_train_stops_early_on_a_validation_plateau():
    # Training pulls w from 0 to 1; validation wants 0.5, so its loss falls, then rises: with
    # patience 3 the loop stops, returning the model of the best validation loss.
    train, validation = jnp.ones((4,)), jnp.full((4,), 0.5)
    result = jll.train(
        _Scalar(jnp.zeros(())),
        _quadratic,
        train,
        optimizer=optax.sgd(0.05),
        steps=500,
        validation=validation,
        validate_every=2,
        patience=3,
    )
    assert result.stopped_early and len(result.train_loss) < 100
    assert abs(float(result.model.w) - 0.5) < 0.05  # one validation interval of sgd steps
    assert result.best_step == result.validation_steps[np.argmin(result.validation_loss)]
    with pytest.raises(ValueError, match="validation"):
        jll.train(_Scalar(jnp.zeros(())), _quadratic, train, steps=5, patience=2)


def test_train_step_under_jit_vmap_and_grad():
    optimizer = optax.adam(1e-2)
    data = jnp.arange(4.0)
    models = _Scalar(jnp.array([0.0, 1.0, 2.0]))
    states = jax.vmap(optimizer.init)(models)
    step = eqx.filter_jit(eqx.filter_vmap(lambda m, s: jll.train_step(m, s, data, _quadratic, optimizer)))
    with jax.numpy_dtype_promotion("standard"):  # optax mixes int32 step counts with floats
        new, _, value = step(models, states)
        for i in range(3):
            model = _Scalar(models.w[i])
            one, _, v = jll.train_step(model, optimizer.init(model), data, _quadratic, optimizer)
            np.testing.assert_allclose(new.w[i], one.w, rtol=1e-15)
            np.testing.assert_allclose(value.value[i], v.value, rtol=1e-15)

    # grad through one sgd step (loss after the step, w.r.t. the data): closed form
    # w' = w − η·2(w − mean d), L' = mean((w' − d)²).
    sgd = optax.sgd(0.1)

    def after(d):
        m, _, _ = jll.train_step(
            _Scalar(jnp.array(0.3)), sgd.init(_Scalar(jnp.array(0.3))), d, _quadratic, sgd
        )
        return _quadratic(m, d).value

    g = jax.jit(jax.grad(after))(data)
    h = 1e-6
    fd = np.array([(after(data.at[i].add(h)) - after(data.at[i].add(-h))) / (2 * h) for i in range(4)])
    np.testing.assert_allclose(g, fd, rtol=1e-7)  # quadratic: central FD exact up to round-off


def test_split_and_segments():
    data = jll.TrajectoryData(
        jnp.broadcast_to(jnp.arange(9.0), (5, 9)), jnp.zeros((5, 9, 2)), jnp.zeros((5, 9, 2))
    )
    train, validation = jll.split(data, 0.4, key=KEY)
    assert train.q.shape[0] == 3 and validation.q.shape[0] == 2
    pieces = jll.segments(data, 3)
    assert pieces.ts.shape == (20, 3)
    np.testing.assert_array_equal(pieces.ts[:4], [[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 7, 8]])


def test_accelerations_export_round_trip():
    # The training path has no host callback: jax.export serializes it and the exported program
    # gives the same numbers (bit for bit: the same compiled computation).
    from jax import export

    model = jll.DeLaN(2, 8, 1, key=KEY)
    f = jax.jit(jax.vmap(lambda q, qd: jll.accelerations(model, q, qd)))
    q, qd = jax.random.normal(KEY, (2, 5, 2))
    exported = export.export(f)(q, qd)
    try:  # bytes need the flatbuffers package, which jaxlag does not depend on
        import flatbuffers  # noqa: F401

        exported = export.deserialize(exported.serialize())
    except ImportError:
        pass
    np.testing.assert_array_equal(exported.call(q, qd), f(q, qd))
