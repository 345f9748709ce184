"""Constrained variational / RATTLE integration (issue 9): invariants, orders, gradients, errors."""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
from jaxlag._variational import LagrangianStructure, lagrangian_structure, simulate_variational

METHOD = {"rattle": jl.Rattle(), "variational": jl.VariationalMidpoint()}

jax.config.update("jax_enable_x64", True)

EPS = float(np.finfo(np.float64).eps)
TIGHT = dict(stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12))


# ----------------------------------------------------------------------------- systems
def pendulum_lagrangian(q, qd, args):
    return 0.5 * args["m"] * jnp.sum(qd**2) - args["m"] * args["g"] * q[1]


def rod(q, args):  # f = r − l: λ = −m l θ̇² − m g cos θ (θ from the downward vertical)
    return jnp.array([jnp.sqrt(q[0] ** 2 + q[1] ** 2) - args["l"]])


PENDULUM = jl.System(pendulum_lagrangian, holonomic=rod)
PENDULUM_ARGS = {"m": 1.3, "g": 9.81, "l": 0.8}


def pendulum_state(theta, l, omega=0.0):
    q = jnp.array([l * jnp.sin(theta), -l * jnp.cos(theta)])
    qd = omega * jnp.array([l * jnp.cos(theta), l * jnp.sin(theta)])
    return q, qd


def double_pendulum():
    g = 9.81

    def lagrangian(q, qd):
        return 0.5 * jnp.sum(qd**2) - g * (q[1] + q[3])

    def links(q):
        return jnp.array([q[0] ** 2 + q[1] ** 2 - 1.0, (q[2] - q[0]) ** 2 + (q[3] - q[1]) ** 2 - 1.0])

    th1, th2, w1, w2 = 1.0, 2.0, 0.5, -0.3
    q0 = jnp.array(
        [math.sin(th1), -math.cos(th1), math.sin(th1) + math.sin(th2), -math.cos(th1) - math.cos(th2)]
    )
    qd0 = jnp.array(
        [
            w1 * math.cos(th1),
            w1 * math.sin(th1),
            w1 * math.cos(th1) + w2 * math.cos(th2),
            w1 * math.sin(th1) + w2 * math.sin(th2),
        ]
    )
    return jl.System(lagrangian, holonomic=links), q0, qd0


def complete_elliptic_k(k):
    a, b = 1.0, math.sqrt(1.0 - k * k)
    for _ in range(30):
        a, b = 0.5 * (a + b), math.sqrt(a * b)
    return math.pi / (2.0 * a)


def early_and_late_error(energy):
    """Largest |E − E₀| over the first and over the last tenth of a run."""
    err = np.abs(np.asarray(energy) - float(energy[0]))
    n = len(err) // 10
    return err[1 : n + 1].max(), err[-n:].max()


# ----------------------------------------------------------------------------- must-shows
def test_double_pendulum_constraints_hold_at_every_step_over_1e5_steps():
    system, q0, qd0 = double_pendulum()
    traj = simulate_variational(system, q0, qd0, dt=1e-3, num_steps=100_000)
    f, f_dot, _ = traj.constraint_residuals
    assert traj.q.shape == (100_001, 4)
    # Every step solves f(q_{k+1}) = 0 by Newton to a residual ≤ 1e-12 before its last update
    # (so ~1e-16 after it) and projects q̇ exactly onto J q̇ = 0; what is left is the round-off of
    # evaluating |x|² − 1 (~4e-16) and J q̇ with |q̇| ≲ 7 (~5e-15).
    assert float(jnp.max(jnp.abs(f))) <= 1e-12
    assert float(jnp.max(jnp.abs(f_dot))) <= 1e-12
    assert int(traj.stats["failed_step"]) == -1
    # Newton starts from an O(h³) extrapolation: two iterations per step suffice throughout.
    assert int(traj.stats["max_newton_iterations"]) <= 3
    # Chaotic motion, yet the energy error stays small (O(h²) = 1e-6 times a sensitivity of
    # ~1e3 for |q̇| up to 7; measured 7.5e-4 of |E| = 6.3): no drift, no stabilization needed.
    energy = traj.energy
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 2e-3


def test_energy_error_bounded_where_runge_kutta_drifts():
    """1e5 steps (≈ 400 periods) of a Cartesian pendulum and of a Kepler orbit at a fixed step."""
    args = {"m": 1.0, "g": 9.81, "l": 1.0}
    q0, qd0 = pendulum_state(2.0, 1.0)
    orbit = jl.System(lambda q, qd: 0.5 * jnp.sum(qd**2) + 1.0 / jnp.sqrt(jnp.sum(q**2)))
    e = 0.5
    k0, kd0 = jnp.array([1 - e, 0.0]), jnp.array([0.0, math.sqrt((1 + e) / (1 - e))])
    n = 100_000
    for system, a, b, h, run_args in [
        (PENDULUM, q0, qd0, 0.01, args),
        (orbit, k0, kd0, 2 * math.pi / 100, None),
    ]:
        vi = simulate_variational(system, a, b, dt=h, num_steps=n, save_every=100, args=run_args)
        early, late = early_and_late_error(vi.energy)
        # Bounded: the error of the last tenth is no larger than that of the first (a linear
        # drift would make it ~10x larger); measured 0.0058 -> 0.0049 and 0.00542 -> 0.00542.
        assert late <= 1.2 * early
        assert late < 1e-2
        ts = jnp.arange(n // 100 + 1, dtype=float) * h * 100
        rk = jl.simulate(
            system,
            a,
            b,
            ts,
            args=run_args,
            solver=diffrax.Tsit5(),
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=h,
            max_steps=n + 10,
        )
        rk_early, rk_late = early_and_late_error(rk.energy)
        # Tsit5 at the same step is far more accurate early on but drifts linearly (×10 over
        # the ×10 longer time: measured 2.7e-7 -> 2.7e-6 and 8.8e-6 -> 8.8e-5).
        assert rk_late >= 5.0 * rk_early
        if run_args is None:  # the Kepler orbit (cheap, unconstrained)
            rk2 = jl.simulate(
                system,
                a,
                b,
                ts,
                solver=diffrax.Midpoint(),
                dt0=h,
                stepsize_controller=diffrax.ConstantStepSize(),
                max_steps=n + 10,
            )
            # The explicit RK of the same (second) order and step ends ~100x worse: the orbit
            # decays (measured 0.28 -> 0.50 of |E| = 0.5).
            assert early_and_late_error(rk2.energy)[1] > 30 * late


@pytest.mark.parametrize("method", ["rattle", "variational"])
def test_spherical_pendulum_angular_momentum_is_conserved_to_roundoff(method):
    m, g, l = 1.3, 9.81, 0.8

    def lagrangian(q, qd):
        return 0.5 * m * jnp.sum(qd**2) - m * g * q[2]

    system = jl.System(lagrangian, holonomic=lambda q: jnp.array([jnp.sum(q**2) - l**2]))
    q0 = jnp.array([l * math.sin(2.0), 0.0, -l * math.cos(2.0)])
    qd0 = jnp.array([0.0, 1.7, 0.0])
    n = 20_000
    traj = simulate_variational(system, q0, qd0, dt=0.01, num_steps=n, save_every=10, method=METHOD[method])
    lz = m * (traj.q[:, 0] * traj.qd[:, 1] - traj.q[:, 1] * traj.qd[:, 0])
    # Discrete Noether: L_d and f are invariant under rotations about z, so L_z of the discrete
    # momenta is exact up to rounding, which adds up at most linearly: with ~10 roundings per
    # step, 10·n·eps·|L_z| = 7e-11; measured 2.2e-14 (rattle) and 3.0e-14 (variational). The
    # KKT path with Tsit5 at the same step loses 7.7e-8 over this time.
    assert float(jnp.max(jnp.abs(lz - lz[0]))) <= 10 * n * EPS * abs(float(lz[0]))


@pytest.mark.parametrize("method,order", [("rattle", 2), ("variational", 2), ("rattle", 4)])
def test_convergence_order_on_the_pendulum_closed_form(method, order):
    """A quarter period after release from rest at θ0 the bob is at the bottom, with the closed
    forms θ̇ = 2√(g/l) sin(θ0/2), λ = −m l θ̇² − m g; the period is 4√(l/g) K(sin(θ0/2))."""
    m, g, l = PENDULUM_ARGS["m"], PENDULUM_ARGS["g"], PENDULUM_ARGS["l"]
    theta0 = 2.0
    quarter = math.sqrt(l / g) * complete_elliptic_k(math.sin(theta0 / 2))
    omega = 2 * math.sqrt(g / l) * math.sin(theta0 / 2)
    q_exact, qd_exact = np.array([0.0, -l]), np.array([-l * omega, 0.0])
    lam_exact = -m * l * omega**2 - m * g
    q0, qd0 = pendulum_state(theta0, l)
    errors = []
    for n in (50, 100, 200):
        # One compilation: 200 steps saved every 50; with h = quarter/n the quarter period is
        # reached at the saved index n/50.
        traj = simulate_variational(
            PENDULUM,
            q0,
            qd0,
            dt=quarter / n,
            num_steps=200,
            save_every=50,
            args=PENDULUM_ARGS,
            method=METHOD[method],
            order=order,
        )
        i = n // 50
        errors.append(
            [
                float(jnp.max(jnp.abs(traj.q[i] - q_exact))),
                float(jnp.max(jnp.abs(traj.qd[i] - qd_exact))),
                abs(float(traj.multipliers[i, 0]) - lam_exact),  # KKT λ at the computed state
                abs(float(traj.stats["multipliers"][i, 0]) - lam_exact),  # the integrator's own
            ]
        )
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    # Measured orders agree with the claim to ±0.01 at these step counts (errors far above
    # round-off); the integrator's discrete multipliers are second order for every composition.
    np.testing.assert_allclose(orders[:, :3], order, atol=0.05)
    np.testing.assert_allclose(orders[:, 3], 2.0, atol=0.05)


# ----------------------------------------------------------------------------- physics
def test_multipliers_follow_the_kkt_sign_convention_with_a_state_dependent_mass_matrix():
    """Polar coordinates (r, θ) with r = l imposed: M(q) = diag(m, m r²), the full Newton path."""
    m, g, l = 1.3, 9.81, 0.8

    def lagrangian(q, qd):
        r, th = q
        return 0.5 * m * (qd[0] ** 2 + r**2 * qd[1] ** 2) + m * g * r * jnp.cos(th)

    system = jl.System(lagrangian, holonomic=lambda q: jnp.array([q[0] - l]))
    assert lagrangian_structure(system, jnp.array([l, 2.0]), jnp.zeros(2)) == (True, False)
    for method in ("rattle", "variational"):
        traj = simulate_variational(
            system,
            jnp.array([l, 2.0]),
            jnp.array([0.0, 0.3]),
            dt=1e-3,
            num_steps=1000,
            save_every=100,
            method=METHOD[method],
        )
        th, thd = traj.q[:, 1], traj.qd[:, 1]
        closed_form = -m * l * thd**2 - m * g * jnp.cos(th)
        # O(h²) = 1e-6 times a sensitivity of ~10-100 for |λ| up to 50; measured 4e-5 (rattle)
        # and 2.7e-4 (variational). The KKT λ at the computed states agree to rounding.
        np.testing.assert_allclose(traj.stats["multipliers"][:, 0], closed_form, atol=1e-3)
        np.testing.assert_allclose(traj.multipliers[:, 0], closed_form, atol=1e-10)
        assert float(jnp.max(jnp.abs(traj.q[:, 0] - l))) <= 1e-12


def test_general_lagrangian_with_constraint_matches_the_kkt_path():
    """A relativistic particle (L not quadratic in q̇) on a circle: Newton in both stages."""
    m, c, k = 1.3, 3.0, 4.0

    def lagrangian(q, qd):
        return -m * c**2 * jnp.sqrt(1 - jnp.sum(qd**2) / c**2) - 0.5 * k * jnp.sum(q**2)

    system = jl.System(lagrangian, holonomic=lambda q: jnp.array([jnp.sum(q**2) - 1.0]))
    q0, qd0 = jnp.array([1.0, 0.0]), jnp.array([0.0, 1.5])
    assert lagrangian_structure(system, q0, qd0) == (False, False)
    traj = simulate_variational(system, q0, qd0, dt=1e-3, num_steps=2000, save_every=1000)
    ref = jl.simulate(system, q0, qd0, jnp.array([0.0, 1.0, 2.0]), **TIGHT)
    # Second-order global error over 2 s at h = 1e-3: measured 5.8e-7 (q), 8.7e-7 (q̇) and
    # 4e-8 relative (λ).
    np.testing.assert_allclose(traj.q, ref.q, atol=5e-6)
    np.testing.assert_allclose(traj.qd, ref.qd, atol=5e-6)
    np.testing.assert_allclose(traj.stats["multipliers"], ref.multipliers, rtol=1e-5)
    f, f_dot, _ = traj.constraint_residuals
    assert float(jnp.max(jnp.abs(f))) <= 1e-12 and float(jnp.max(jnp.abs(f_dot))) <= 1e-12
    with pytest.raises(ValueError, match="quadratic in q̇"):
        simulate_variational(system, q0, qd0, dt=1e-3, num_steps=10, method=jl.Rattle())
    # Unconstrained, the velocity stage is the plain inverse Legendre transform (Newton in q̇).
    # The potential is central, so the angular momentum q × p of the relativistic momenta
    # p = γ m q̇ is a discrete Noether invariant: exact up to rounding (bound: 10 roundings per
    # step, 1e-11; measured 3.7e-14), while the energy error stays O(h²) (measured 2.9e-8).
    n = 2000
    traj = simulate_variational(jl.System(lagrangian), q0, qd0, dt=1e-3, num_steps=n, save_every=10)
    p = traj.momenta
    lz = traj.q[:, 0] * p[:, 1] - traj.q[:, 1] * p[:, 0]
    assert float(jnp.max(jnp.abs(lz - lz[0]))) <= 10 * n * EPS * abs(float(lz[0]))
    assert float(jnp.max(jnp.abs(traj.energy - traj.energy[0]))) < 1e-6


def test_rheonomic_constraint_moving_pivot():
    m, g, l, a, w = 1.3, 9.81, 0.8, 0.1, 5.0

    def rod_on_shaker(q, t):
        return jnp.array([jnp.sqrt((q[0] - a * jnp.sin(w * t)) ** 2 + q[1] ** 2) - l])

    system = jl.System(lambda q, qd: 0.5 * m * jnp.sum(qd**2) - m * g * q[1], holonomic=rod_on_shaker)
    q0 = jnp.array([l * math.sin(0.5), -l * math.cos(0.5)])
    qd0 = jnp.array([a * w, 0.0])  # moves with the pivot: ḟ = 0
    ref = jl.simulate(system, q0, qd0, jnp.array([0.0, 1.0, 2.0]), **TIGHT)
    for method in ("rattle",):  # explicit positions; the midpoint path shares the f_t handling
        traj = simulate_variational(
            system, q0, qd0, dt=1e-3, num_steps=2000, save_every=1000, method=METHOD[method]
        )
        f, f_dot, _ = traj.constraint_residuals  # ḟ = J q̇ + ∂f/∂t
        assert float(jnp.max(jnp.abs(f))) <= 1e-12 and float(jnp.max(jnp.abs(f_dot))) <= 1e-12
        # O(h²) global error: measured 4.5e-7 (q), 5e-6 (q̇), 2e-5 (λ ≈ −9).
        np.testing.assert_allclose(traj.q, ref.q, atol=5e-6)
        np.testing.assert_allclose(traj.qd, ref.qd, atol=5e-5)
        np.testing.assert_allclose(traj.stats["multipliers"], ref.multipliers, atol=2e-4)


@pytest.mark.parametrize("method", ["rattle", "variational"])
def test_dissipation_by_discrete_lagrange_dalembert_is_second_order(method):
    k, c = 4.0, 0.3
    system = jl.System(
        lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * k * q[0] ** 2, dissipation=lambda q, qd: 0.5 * c * qd[0] ** 2
    )
    zeta, wd = c / 2, math.sqrt(k - c * c / 4)
    t1 = 3.0
    exact = math.exp(-zeta * t1) * (math.cos(wd * t1) + zeta / wd * math.sin(wd * t1))
    errors = []
    for n in (100, 200, 400):  # one compilation; t1 is reached at the saved index n/100
        traj = simulate_variational(
            system,
            jnp.array([1.0]),
            jnp.array([0.0]),
            dt=t1 / n,
            num_steps=400,
            save_every=100,
            method=METHOD[method],
        )
        errors.append(abs(float(traj.q[n // 100, 0]) - exact))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(orders, 2.0, atol=0.05)  # measured 2.000 and 2.006


def test_structure_analysis_is_conservative():
    q, qd = jnp.array([0.3, -0.2]), jnp.array([0.1, 0.4])
    cartesian = jl.System(lambda q, qd: 0.5 * jnp.sum(qd**2) - 9.81 * q[1])
    assert lagrangian_structure(cartesian, q, qd) == LagrangianStructure(True, True)
    # Quadratic, but written so that no structural analysis can see it: a slower path, and
    # method=jl.Rattle() checks quadraticity numerically instead.
    hidden = jl.System(
        lambda q, qd: 0.5 * jnp.linalg.norm(qd) ** 2 - 9.81 * q[1],
        holonomic=lambda q: jnp.array([jnp.sum(q**2) - 0.13]),
    )
    assert lagrangian_structure(hidden, q, qd) == LagrangianStructure(False, False)
    q0, qd0 = jnp.array([0.3, -0.2]), jnp.array([0.2, 0.3])
    a = simulate_variational(hidden, q0, qd0, dt=1e-3, num_steps=100, method=jl.Rattle())
    b = simulate_variational(
        jl.System(cartesian.lagrangian, holonomic=hidden.holonomic),
        q0,
        qd0,
        dt=1e-3,
        num_steps=100,
        method=jl.Rattle(),
    )
    np.testing.assert_allclose(a.q, b.q, atol=1e-13)  # the same scheme, solved differently


# ----------------------------------------------------------------------------- transformations
@pytest.mark.parametrize("method", ["rattle", "variational"])
def test_gradient_through_implicit_steps_matches_central_differences(method):
    def loss(params):
        q0, qd0 = pendulum_state(params["theta"], params["args"]["l"], params["omega"])
        traj = simulate_variational(
            PENDULUM,
            q0,
            qd0,
            dt=params["dt"],
            num_steps=200,
            save_every=20,
            args=params["args"],
            method=METHOD[method],
        )
        return jnp.sum(traj.q[:, 0] ** 2) + jnp.sum(traj.qd[:, 1]) + 0.01 * jnp.sum(traj.stats["multipliers"])

    params = jax.tree.map(
        jnp.asarray, {"theta": 1.2, "omega": 0.4, "dt": 0.005, "args": {"m": 1.3, "g": 9.81, "l": 0.8}}
    )
    grads = jax.grad(loss)(params)
    compiled = jax.jit(loss)
    for path in [("theta",), ("omega",), ("dt",), ("args", "g"), ("args", "l"), ("args", "m")]:

        def shifted(delta):
            p = jax.tree.map(lambda x: x, params)
            node = p
            for key in path[:-1]:
                node = node[key]
            node[path[-1]] = node[path[-1]] + delta
            return compiled(p)

        x = params
        for key in path:
            x = x[key]
        step = 1e-4 * abs(float(x))
        fd = (float(shifted(step)) - float(shifted(-step))) / (2 * step)
        g = grads
        for key in path:
            g = g[key]
        # With a relative step of 1e-4, central differences err by ~(1e-4)²·f'''/f' ≈ 1e-8 (up to
        # 1e-7 for dt, which sets the final time 200·dt) plus rounding ~eps·|loss|/step; the
        # implicit-function-theorem gradient is exact up to the Newton tolerance. Measured
        # agreement ≤ 1e-8 relative, 4e-7 for dt.
        rel = abs(float(g) - fd) / max(1.0, abs(fd))
        assert rel <= 1e-6, (path, float(g), fd)


def test_vmap_equals_loop_and_jit_returns_a_trajectory():
    thetas = jnp.linspace(0.3, 2.5, 4)

    def run(theta):
        q0, qd0 = pendulum_state(theta, PENDULUM_ARGS["l"])
        return simulate_variational(
            PENDULUM, q0, qd0, dt=0.005, num_steps=400, save_every=40, args=PENDULUM_ARGS
        )

    batch = jax.vmap(run)(thetas)
    assert batch.q.shape == (4, 11, 2) and batch.energy.shape == (4, 11)
    assert batch.stats["multipliers"].shape == (4, 11, 1)
    loop = np.stack([np.asarray(jax.jit(run)(th).q) for th in thetas])
    # Under vmap Newton iterates until every member converges, so members may take one more
    # (converged) iteration than alone: agreement to rounding, measured 1e-15.
    np.testing.assert_allclose(batch.q, loop, atol=1e-12)


def test_closure_over_a_traced_parameter():
    def final_x(g):
        system = jl.System(
            lambda q, qd: 0.5 * jnp.sum(qd**2) - g * q[1],
            holonomic=lambda q: jnp.array([jnp.sum(q**2) - 1.0]),
        )
        q0, qd0 = pendulum_state(1.0, 1.0)
        return simulate_variational(system, q0, qd0, dt=0.01, num_steps=50).q[-1, 0]

    compiled = jax.jit(final_x)  # the closure captures a tracer here too
    fd = (compiled(9.81 + 1e-4) - compiled(9.81 - 1e-4)) / 2e-4
    np.testing.assert_allclose(jax.grad(final_x)(9.81), fd, rtol=1e-6)


# ----------------------------------------------------------------------------- errors
def test_newton_failure_raises_a_clear_error():
    system, q0, _ = double_pendulum()
    qd0 = jnp.array(
        [
            3.5 * math.cos(1.0),
            3.5 * math.sin(1.0),
            3.5 * math.cos(1.0) - 4.3 * math.cos(2.0),
            3.5 * math.sin(1.0) - 4.3 * math.sin(2.0),
        ]
    )
    with pytest.raises(Exception, match="did not converge.*reduce dt"):
        simulate_variational(system, q0, qd0, dt=0.2, num_steps=20)
    traj = simulate_variational(system, q0, qd0, dt=0.2, num_steps=20, throw=False)
    assert traj.result != diffrax.RESULTS.successful
    assert int(traj.stats["failed_step"]) == 0
    ok = simulate_variational(system, q0, qd0, dt=0.01, num_steps=20)  # a smaller step is fine
    assert int(ok.stats["failed_step"]) == -1


def test_unsupported_and_invalid_input():
    q0, qd0 = pendulum_state(0.5, 0.8)
    rolling = jl.System(pendulum_lagrangian, velocity_constraints=lambda q, qd: qd[:1])
    with pytest.raises(NotImplementedError, match="holonomic constraints only"):
        simulate_variational(rolling, q0, qd0, dt=0.01, num_steps=10, args=PENDULUM_ARGS)
    with pytest.raises(ValueError, match="multiple of save_every"):
        simulate_variational(PENDULUM, q0, qd0, dt=0.01, num_steps=10, save_every=3, args=PENDULUM_ARGS)
    with pytest.raises(TypeError, match=r"method=jl.Rattle\(\), method=jl.VariationalMidpoint\(\)"):
        simulate_variational(PENDULUM, q0, qd0, dt=0.01, num_steps=10, method="rattle", args=PENDULUM_ARGS)
    with pytest.raises(ValueError, match="order"):
        simulate_variational(PENDULUM, q0, qd0, dt=0.01, num_steps=10, order=3, args=PENDULUM_ARGS)
    with pytest.raises(ValueError, match="off the constraint manifold"):
        simulate_variational(PENDULUM, q0 * 1.01, qd0, dt=0.01, num_steps=10, args=PENDULUM_ARGS)
