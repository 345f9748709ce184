r"""A first-class control input: ``actuation`` ``Q_u(q, q̇, u, t)`` and a ``control`` law on a System.

Convention: ``M q̈ = F + Q_u(q, q̇, u, t) + Jᵀλ``; ``linearize`` gives ``A = ∂(q̇, q̈)/∂(q, q̇)`` with
``u`` held (the open loop), ``B = ∂(q̇, q̈)/∂u`` and the law's feedback ``F = ∂u/∂(q, q̇)``.

Closed forms:

* pendulum ``m l² θ̈ = −m g l sin θ + u``: ``B = (0, 1/(m l²))``, and about an angle ``θ₀`` held by
  the torque ``u₀ = m g l sin θ₀``, ``A = [[0, 1], [−(g/l) cos θ₀, 0]]``;
* cart-pole with a uniform pole, θ from upright: ``M_c = [[M+m, ½ml], [½ml, ⅓ml²]]`` and
  ``M_c δq̈ − diag(0, ½mgl) δq = (u, 0)``, so ``B = (0, M_c⁻¹(1, 0))``.

Tolerances: linearizations are exact derivatives (autodiff) of O(10) quantities, so they agree
with closed forms to round-off; 1e-12 leaves a few hundred ulps for the KKT solve and the
tangent basis. Simulated quantities at rtol = atol = 1e-10 (the default) are compared to 1e-8.
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.linalg

import jaxlag as jl
import jaxlag.systems as systems
from jaxlag import analysis, inputs

jax.config.update("jax_enable_x64", True)

G = 9.81
M_P, L_P = 2.0, 0.5  # the torque-driven pendulum


def _pendulum_lagrangian(q, qd):
    return 0.5 * M_P * L_P**2 * qd[0] ** 2 + M_P * G * L_P * jnp.cos(q[0])


def _torque(q, qd, u):  # Q_u = (u,): a torque on θ
    return jnp.reshape(u, (1,))


def _state_feedback(q, qd, t, args):  # u = −K y + d(t): gains and a time table in args
    return -jnp.dot(args["K"], jnp.concatenate([q, qd])) + args["d"](t)


PENDULUM = jl.System(_pendulum_lagrangian, actuation=_torque, control=_state_feedback)


def _angle_form(theta0):
    a = np.array([[0.0, 1.0], [-G / L_P * np.cos(theta0), 0.0]])
    b = np.array([[0.0], [1.0 / (M_P * L_P**2)]])
    return a, b


def test_input_matrix_of_a_torque_driven_pendulum():
    # About θ₀ = 0.4 held by u₀ = m g l sin θ₀: A and B of the closed form; F = −K of the law.
    theta0 = 0.4
    u0 = M_P * G * L_P * np.sin(theta0)
    plant = PENDULUM.with_control(None)
    lin = analysis.linearize(plant, jnp.array([theta0]), u=u0)
    a, b = _angle_form(theta0)
    np.testing.assert_allclose(lin.state_matrix, a, atol=1e-12)
    np.testing.assert_allclose(lin.input_matrix, b, atol=1e-12)
    assert lin.feedback_matrix is None and float(lin.input) == pytest.approx(u0, rel=1e-15)
    # equilibrium: q̈ = 0 with the holding torque, which delivers the power q̇·Q_u = θ̇ u₀
    held = plant.with_control(lambda q, qd: u0)
    np.testing.assert_allclose(held.accelerations([theta0], [0.0]), [0.0], atol=1e-12)
    np.testing.assert_allclose(held.input_power([theta0], [0.7]), 0.7 * u0, rtol=1e-14)
    np.testing.assert_allclose(held.control_input([theta0], [0.7]), u0, rtol=1e-14)
    # With the law: u₀ = −K y* + d(t) is the law's value; A is the open loop, F = −K.
    K = np.array([30.0, 5.0])
    args = {"K": K, "d": inputs.ZeroOrderHold(np.array([0.0, 1.0]), np.array([u0, 0.0]))}
    lin = analysis.linearize(PENDULUM, jnp.array([theta0]), args=args)
    np.testing.assert_allclose(lin.input, u0 - K[0] * theta0, rtol=1e-14)
    np.testing.assert_allclose(lin.state_matrix, a, atol=1e-12)
    np.testing.assert_allclose(lin.feedback_matrix, -K[None], atol=1e-12)
    np.testing.assert_allclose(lin.closed_loop_matrix, a - b @ K[None], atol=1e-12)
    expected = np.linalg.eigvals(a - b @ K[None])
    np.testing.assert_allclose(
        np.sort_complex(lin.closed_loop_eigenvalues), np.sort_complex(expected), atol=1e-12
    )


def test_cart_pole_input_matrix_against_the_textbook():
    M, m, l = 1.0, 0.3, 0.8
    args = {"M": M, "m": m, "l": l, "g": G}
    mass = np.array([[M + m, 0.5 * m * l], [0.5 * m * l, m * l**2 / 3]])
    a = np.zeros((4, 4))
    a[:2, 2:] = np.eye(2)
    a[2:, :2] = np.linalg.solve(mass, np.diag([0.0, 0.5 * m * G * l]))
    b = np.concatenate([np.zeros(2), np.linalg.solve(mass, [1.0, 0.0])])[:, None]
    # u₀ = the parameter force (0); tests/test_analysis.py checks the inputs= selector.
    lin = analysis.linearize(systems.cart_pole(), jnp.zeros(2), args=args)
    np.testing.assert_allclose(lin.state_matrix, a, atol=1e-12)
    np.testing.assert_allclose(lin.input_matrix, b, atol=1e-12)


def test_constrained_actuation_matches_the_angle_form():
    # The same torque-driven pendulum in Cartesian (x, y) with the rod |r| = l: the torque u is
    # the force u (−y, x)/l² perpendicular to the rod. About the held angle θ₀ the two
    # linearizations are related by T = ∂(x, y, ẋ, ẏ)/∂(θ, θ̇): A_c T = T A_a (the fields are
    # conjugate and vanish there), B_c = T B_a (B lies in the tangent space), F_c T = F_a, and the
    # reduced closed loops have the same spectrum.
    theta0, K = 0.4, np.array([30.0, 5.0])
    u0 = M_P * G * L_P * np.sin(theta0)

    def lagrangian(q, qd):
        return 0.5 * M_P * jnp.sum(qd**2) - M_P * G * q[1]

    def rod(q):
        return jnp.reshape(jnp.sqrt(q[0] ** 2 + q[1] ** 2) - L_P, (1,))

    def torque(q, qd, u):
        return jnp.reshape(u, ()) * jnp.stack([-q[1], q[0]]) / L_P**2

    def law(q, qd):  # u = u₀ − K (θ − θ₀, θ̇) with θ = atan2(x, −y), θ̇ = (x ẏ − y ẋ)/l²
        theta = jnp.arctan2(q[0], -q[1])
        theta_dot = (q[0] * qd[1] - q[1] * qd[0]) / L_P**2
        return u0 - K[0] * (theta - theta0) - K[1] * theta_dot

    cartesian = jl.System(lagrangian, holonomic=rod, actuation=torque, control=law)
    q = L_P * jnp.array([np.sin(theta0), -np.cos(theta0)])
    lin = analysis.linearize(cartesian, q, jnp.zeros(2))
    np.testing.assert_allclose(lin.input, u0, rtol=1e-14)
    c, s = np.cos(theta0), np.sin(theta0)
    T = np.zeros((4, 2))
    T[:2, 0] = T[2:, 1] = L_P * np.array([c, s])
    a, b = _angle_form(theta0)
    np.testing.assert_allclose(lin.state_matrix @ T, T @ a, atol=1e-12)
    np.testing.assert_allclose(lin.input_matrix, T @ b, atol=1e-12)
    np.testing.assert_allclose(lin.basis @ lin.reduced_input_matrix, lin.input_matrix, atol=1e-12)
    np.testing.assert_allclose(lin.feedback_matrix @ T, -K[None], atol=1e-12)
    np.testing.assert_allclose(
        np.sort_complex(lin.closed_loop_eigenvalues),
        np.sort_complex(np.linalg.eigvals(a - b @ K[None])),
        atol=1e-12,
    )


# --------------------------------------------------------------------------------------------
# The LQR-balanced cart-pole under a time-table disturbance: one System for all of it
# --------------------------------------------------------------------------------------------


def _lqr_cart_pole():
    def law(q, qd, t, args):  # u = −K (x, θ, ẋ, θ̇) + push(t)
        return -jnp.dot(args["K"], jnp.concatenate([q, qd])) + args["push"](t)

    return systems.cart_pole(control=law)


PUSH_TIMES = np.array([0.0, 1.0, 1.3, 5.0])


def test_lqr_cart_pole_under_a_pushed_table():
    cart = _lqr_cart_pole()
    quiet = inputs.ZeroOrderHold(PUSH_TIMES, np.zeros(4))
    args = {"K": jnp.zeros(4), "push": quiet}
    lin = analysis.linearize(cart, jnp.zeros(2), args=args)
    A, B = np.asarray(lin.state_matrix), np.asarray(lin.input_matrix)
    assert lin.stability() == "unstable"
    P = scipy.linalg.solve_continuous_are(A, B, np.diag([1.0, 10.0, 1.0, 1.0]), np.array([[0.1]]))
    K = np.linalg.solve(np.array([[0.1]]), B.T @ P)[0]
    closed = analysis.linearize(cart, jnp.zeros(2), args={**args, "K": jnp.asarray(K)})
    np.testing.assert_allclose(closed.closed_loop_matrix, A - np.outer(B, K), atol=1e-12)
    assert np.all(closed.closed_loop_eigenvalues.real < -1.0)

    # A push of amplitude a on the cart from t = 1 to 1.3 s, starting from θ₀ = a/100: the
    # small ones are compared with the linear prediction, the large one must stay balanced.
    amplitudes = jnp.array([0.02, 0.04, 5.0])
    ts = np.linspace(0.0, 5.0, 51)  # includes the push's breakpoints 1.0 and 1.3

    @jax.jit
    def run(amplitude):
        push = inputs.ZeroOrderHold(PUSH_TIMES, jnp.stack([0.0, amplitude, 0.0, 0.0]))
        traj = jl.simulate(
            cart,
            jnp.stack([0.0, amplitude / 100]),
            jnp.zeros(2),
            ts,
            args={"K": jnp.asarray(K), "push": push},
        )
        return traj.q, traj.qd, traj.controls

    q, qd, u = jax.vmap(run)(amplitudes)
    # Linear prediction: δẏ = (A − BK) δy + B d(t), d piecewise constant: exact by expm.
    aug = np.zeros((5, 5))
    aug[:4, :4], aug[:4, 4] = A - np.outer(B, K), B[:, 0]
    errors = []
    for k, a in enumerate(np.asarray(amplitudes[:2])):
        y = np.array([0.0, a / 100, 0.0, 0.0])
        linear = [y]
        for t0, t1 in zip(ts[:-1], ts[1:]):
            y = (scipy.linalg.expm(aug * (t1 - t0)) @ np.append(y, a if 1.0 <= t0 < 1.3 else 0.0))[:4]
            linear.append(y)
        linear = np.array(linear)
        nonlinear = np.concatenate([q[k], qd[k]], axis=1)
        errors.append(np.max(np.abs(nonlinear - linear)) / np.max(np.abs(linear)))
        # The controls along the trajectory are the law's: −K y + push(t).
        push = np.where((ts >= 1.0) & (ts < 1.3), a, 0.0)
        np.testing.assert_allclose(u[k], -nonlinear @ K + push, atol=1e-12)
    print(f"linear vs nonlinear closed loop: {errors[0]:.1e}, {errors[1]:.1e} of the excursion")
    # The cart-pole is odd under (x, θ, u) → −(x, θ, u), so the neglected terms are cubic: the
    # relative difference is O(a²) (measured 1.2e-7 at a = 0.02 N, θ ≲ 3e-3 rad) and quadruples
    # when the amplitude doubles, which also shows the solver's error (rtol = atol = 1e-10) is
    # far below it. 1e-5 bounds it with room; the ratio is 4 to ±10%.
    assert max(errors) < 1e-5, errors
    assert 3.6 < errors[1] / errors[0] < 4.4, errors
    # The large push (5 N for 0.3 s, starting at θ₀ = 0.05 rad) stays balanced and recovers:
    # 3.7 s after the push the slowest closed-loop mode (Re s ≈ −1.26) has decayed e^{−4.6} ≈ 1/100.
    assert float(jnp.max(jnp.abs(q[1, :, 1]))) < 0.5
    assert float(jnp.max(jnp.abs(q[1, -1]))) < 0.05 and float(jnp.max(jnp.abs(qd[1, -1]))) < 0.05


# --------------------------------------------------------------------------------------------
# Trajectory optimization through a table of inputs
# --------------------------------------------------------------------------------------------

T_KNOTS = np.linspace(0.0, 1.0, 6)
OPEN_LOOP = PENDULUM.with_control(lambda q, qd, t, args: args["tau"](t))  # u = τ(t), a table


def _final_cost(values):
    end = jl.simulate(
        OPEN_LOOP,
        jnp.zeros(1),
        jnp.zeros(1),
        jnp.array([0.0, 1.0]),
        args={"tau": inputs.PiecewiseLinear(T_KNOTS, values)},
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12),
    )
    return (end.q[-1, 0] - 1.0) ** 2 + 0.1 * end.qd[-1, 0] ** 2


def test_trajectory_optimization_through_a_table():
    cost_and_grad = jax.jit(jax.value_and_grad(_final_cost))  # one program for all of it

    def cost(v):
        return float(cost_and_grad(v)[0])

    values = jnp.linspace(1.0, -1.0, 6)
    value, grad = cost_and_grad(values)
    # Central differences at h = 1e-5: truncation O(h²) ≈ 1e-10, and the solver's error
    # (rtol 1e-12) over 2h gives ≈ 1e-12/1e-5 = 1e-7 relative.
    h = 1e-5
    fd = np.array([(cost(values + h * e) - cost(values - h * e)) / (2 * h) for e in np.eye(6)])
    relative = np.max(np.abs(np.asarray(grad) - fd)) / np.max(np.abs(fd))
    print(f"table gradient vs central differences: relative error {relative:.1e}")
    assert relative < 1e-6, relative
    optimizer = optax.adam(0.3)
    state = optimizer.init(values)
    history = [float(value)]
    for _ in range(5):
        with jax.numpy_dtype_promotion("standard"):  # optax mixes int32 step counts with floats
            updates, state = optimizer.update(grad, state)
        values = optax.apply_updates(values, updates)
        value, grad = cost_and_grad(values)
        history.append(float(value))
    assert history[-1] < 0.5 * history[0], history


# --------------------------------------------------------------------------------------------
# Transformations: jit, vmap over gains, grad with respect to gains
# --------------------------------------------------------------------------------------------


def test_jit_vmap_and_grad_of_a_controlled_simulation():
    quiet = inputs.ZeroOrderHold(np.array([0.0, 1.0]), np.zeros(2))
    ts = jnp.array([0.0, 0.5, 1.0])

    def final_angle(K):
        traj = jl.simulate(PENDULUM, jnp.array([0.3]), jnp.zeros(1), ts, args={"K": K, "d": quiet})
        return traj.q[-1, 0]

    # One vmapped program: three gains, and the central differences about the first.
    h = 1e-5
    K0 = np.array([20.0, 2.0])
    gains = jnp.asarray(
        np.stack([K0, [40.0, 4.0], [80.0, 8.0], *(K0 + h * np.eye(2)), *(K0 - h * np.eye(2))])
    )
    values, grads = jax.jit(jax.vmap(jax.value_and_grad(final_angle)))(gains)
    values, grads = np.asarray(values), np.asarray(grads)
    # Stiffer gains pull the pendulum closer to θ = 0 within 1 s.
    assert abs(values[2]) < abs(values[1]) < abs(values[0])
    fd = (values[3:5] - values[5:7]) / (2 * h)
    # default tolerance 1e-10 in the run: central differences good to ~1e-10/h = 1e-5 relative
    relative = np.max(np.abs(grads[0] - fd)) / np.max(np.abs(fd))
    print(f"gain gradient vs central differences: relative error {relative:.1e}")
    assert relative < 1e-4, relative


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------


def test_bad_control_input_is_named():
    with pytest.raises(ValueError, match="needs an `actuation`"):
        jl.System(_pendulum_lagrangian, control=lambda q, qd: 0.0)
    with pytest.raises(ValueError, match="needs an `actuation`"):
        jl.System(_pendulum_lagrangian).with_control(lambda q, qd: 0.0)
    with pytest.raises(TypeError, match=r"3 positional argument\(s\) \(q, qd, u\)"):
        jl.System(_pendulum_lagrangian, actuation=lambda q, qd: q)
    plant = jl.System(_pendulum_lagrangian, actuation=_torque)
    with pytest.raises(ValueError, match="no control law"):
        jl.simulate(plant, jnp.zeros(1), jnp.zeros(1), jnp.array([0.0, 0.1]))
    with pytest.raises(ValueError, match="no control law; give the input"):
        analysis.linearize(plant, jnp.zeros(1))
    with pytest.raises(ValueError, match="scalar or a 1-D array"):
        plant.with_control(lambda q, qd: jnp.zeros((2, 2))).check(jnp.zeros(1), jnp.zeros(1))
    wrong = jl.System(_pendulum_lagrangian, actuation=lambda q, qd, u: u, control=lambda q, qd: jnp.zeros(2))
    with pytest.raises(ValueError, match=r"like q; with u of shape \(2,\) it returned shape \(2,\)"):
        wrong.check(jnp.zeros(1), jnp.zeros(1))
    with pytest.raises(ValueError, match="no `actuation`"):
        analysis.linearize(jl.System(_pendulum_lagrangian), jnp.zeros(1), u=1.0)
    with pytest.raises(ValueError, match="No feedback matrix"):
        _ = analysis.linearize(plant, jnp.zeros(1), u=0.0).closed_loop_matrix


def test_variational_integrator_and_captured_values_see_the_control():
    # ẍ = −x + u with u = k: x(1) = k (1 − cos 1). The variational integrator applies the
    # actuation (second order, dt = 0.01: error ~1e-5 relative); a control law closing over a
    # traced k is differentiated, under jit, like a force function closing over it.
    def lagrangian(q, qd):
        return 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2

    def driven(k):
        return jl.System(lagrangian, actuation=lambda q, qd, u: jnp.stack([u]), control=lambda q, qd: k)

    run = jl.simulate_variational(driven(1.0), jnp.zeros(1), jnp.zeros(1), dt=0.01, num_steps=100)
    np.testing.assert_allclose(run.q[-1, 0], 1 - np.cos(1.0), rtol=1e-4)

    def final(k):
        return jl.simulate(driven(k), jnp.zeros(1), jnp.zeros(1), jnp.array([0.0, 1.0])).q[-1, 0]

    np.testing.assert_allclose(jax.jit(jax.grad(final))(1.0), 1 - np.cos(1.0), rtol=1e-8)


MODES = ("eager", "jit", "vmap")


def _in_mode(mode, fn, x):
    if mode == "eager":
        return jax.block_until_ready(fn(x))
    if mode == "jit":
        return jax.block_until_ready(jax.jit(fn)(x))
    return jax.block_until_ready(jax.vmap(fn)(x[None]))


def _stacked(q, qd, u):  # Q_u = (u,) for a scalar u; a u of shape (2,) makes it (1, 2)
    return jnp.stack([u])


def _two_inputs(q, qd):
    return jnp.zeros(2)


def _nan_after_half_a_second(q, qd, t):
    return jnp.where(t > 0.5, jnp.nan, -5.0 * q[0])


_PLANT = jl.System(_pendulum_lagrangian, actuation=_stacked)


@pytest.mark.parametrize("mode", MODES)
def test_control_law_of_the_wrong_shape_is_named(mode):
    # Before: "The actuation function must return ... shape (1,) like q; with u of shape (2,) it
    # returned shape (1, 2)": the actuation was blamed for the control law's u. The check runs
    # while tracing: the same ValueError in every mode.
    def run(theta0):
        return jl.simulate(_PLANT.with_control(_two_inputs), theta0, jnp.zeros(1), jnp.array([0.0, 0.1])).q

    with pytest.raises(ValueError, match=r"The control law gives u of shape \(2,\), which the actuation"):
        _in_mode(mode, run, jnp.array([0.3]))
    # An actuation that cannot take the law's u at all: the error it raises, under the law's name.
    raising = jl.System(
        _pendulum_lagrangian, actuation=lambda q, qd, u: jnp.stack([u, 0.0])[:1], control=_two_inputs
    )
    with pytest.raises(ValueError, match=r"The control law gives u of shape \(2,\).* raised"):
        raising.check(jnp.zeros(1), jnp.zeros(1))


@pytest.mark.parametrize("mode", MODES)
def test_control_law_returning_nan_is_named(mode):
    # Before: "the accelerations q̈ (... or a force or dissipation function returned NaN)" for a
    # system that has neither. The diagnosis now evaluates each force function on its own.
    controlled = _PLANT.with_control(_nan_after_half_a_second)

    def run(theta0):
        return jl.simulate(controlled, theta0, jnp.zeros(1), jnp.array([0.0, 1.0])).q

    named = r"at t = 0\.5.*the control law's input u = control\(q, q̇, \[t\], \[args\]\).* is non-finite"
    if mode == "eager":
        with pytest.raises(jl.SimulationError, match=named):
            _in_mode(mode, run, jnp.array([0.3]))
        return
    # Compiled: the static cause; the record carries the state, and its full message names the law.
    with pytest.raises(Exception, match="equations of motion became non-finite"):
        _in_mode(mode, run, jnp.array([0.3]))
    if mode == "jit":
        kept = jax.jit(lambda x: jl.simulate(controlled, x, jnp.zeros(1), jnp.array([0.0, 1.0]), throw=False))
        with pytest.raises(jl.SimulationError, match=named):
            kept(jnp.array([0.3])).raise_if_failed()
