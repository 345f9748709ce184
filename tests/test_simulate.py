"""Unconstrained simulation against closed forms (core issue)."""

import math

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl

# Tsit5 at rtol = atol = 1e-12 keeps the global error of these O(1) problems over a few periods
# near 1e-10; the tolerances below leave a factor of ~10-100 for error accumulation.
TIGHT = dict(stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12))


def harmonic(q, qd, args):
    return 0.5 * args["m"] * qd[0] ** 2 - 0.5 * args["k"] * q[0] ** 2


def pendulum(q, qd, args):
    g, l = args["g"], args["l"]
    return 0.5 * l**2 * qd[0] ** 2 + g * l * jnp.cos(q[0])


def complete_elliptic_k(k):
    """K(k) = π / (2 AGM(1, √(1−k²))) by the arithmetic-geometric mean."""
    a, b = 1.0, math.sqrt(1.0 - k * k)
    for _ in range(30):
        a, b = 0.5 * (a + b), math.sqrt(a * b)
    return math.pi / (2.0 * a)


def test_harmonic_oscillator_matches_exact_solution():
    args = {"m": 2.0, "k": 8.0}
    omega = 2.0
    ts = jnp.linspace(0.0, 10.0, 101)
    traj = jl.simulate(jl.System(harmonic), [0.3], [-0.5], ts, args=args, **TIGHT)
    exact = 0.3 * jnp.cos(omega * ts) - 0.5 / omega * jnp.sin(omega * ts)
    exact_v = -0.3 * omega * jnp.sin(omega * ts) - 0.5 * jnp.cos(omega * ts)
    np.testing.assert_allclose(traj.q[:, 0], exact, atol=1e-9)
    np.testing.assert_allclose(traj.qd[:, 0], exact_v, atol=1e-9)
    np.testing.assert_allclose(traj.accelerations[:, 0], -(omega**2) * traj.q[:, 0], atol=1e-12)


@pytest.mark.parametrize("theta0", [1e-3, 0.5, 2.5])
def test_pendulum_period_is_the_elliptic_integral(theta0):
    g, l = 9.81, 0.7
    period = 4.0 * math.sqrt(l / g) * complete_elliptic_k(math.sin(theta0 / 2.0))
    if theta0 < 1e-2:  # small-angle limit 2π√(l/g)(1 + θ0²/16) agrees to O(θ0⁴)
        assert abs(period / (2 * math.pi * math.sqrt(l / g)) - (1 + theta0**2 / 16)) < 1e-12
    ts = jnp.array([0.0, period / 2, period, 3 * period])
    traj = jl.simulate(jl.System(pendulum), [theta0], [0.0], ts, args={"g": g, "l": l}, **TIGHT)
    # Half a period later the pendulum is at −θ0 at rest; after whole periods, back at +θ0.
    np.testing.assert_allclose(traj.q[:, 0], [theta0, -theta0, theta0, theta0], atol=1e-9)
    np.testing.assert_allclose(traj.qd[:, 0], 0.0, atol=1e-8)


def test_energy_function_is_conserved():
    args = {"g": 9.81, "l": 1.0}
    ts = jnp.linspace(0.0, 20.0, 201)
    traj = jl.simulate(jl.System(pendulum), [2.0], [1.0], ts, args=args, **TIGHT)
    h = traj.energy
    # h = ½ l² θ̇² − g l cos θ: the energy function of this Lagrangian is the mechanical energy.
    np.testing.assert_allclose(
        h, 0.5 * traj.qd[:, 0] ** 2 - 9.81 * jnp.cos(traj.q[:, 0]), rtol=1e-14, atol=1e-13
    )
    assert jnp.max(jnp.abs(h / h[0] - 1.0)) < 1e-10


def kepler(q, qd, args):
    r, th = q
    rd, thd = qd
    return 0.5 * args["m"] * (rd**2 + r**2 * thd**2) + args["k"] / r


def test_kepler_orbit_closes_with_the_right_period_and_conserves_angular_momentum():
    m, k = 1.5, 3.0
    mu = k / m
    a, e = 1.0, 0.5
    r_p = a * (1 - e)
    v_p = math.sqrt(mu * (1 + e) / (a * (1 - e)))
    period = 2 * math.pi * math.sqrt(a**3 / mu)
    ts = jnp.linspace(0.0, period, 50)
    traj = jl.simulate(jl.System(kepler), [r_p, 0.0], [0.0, v_p / r_p], ts, args={"m": m, "k": k}, **TIGHT)
    np.testing.assert_allclose(traj.q[-1], [r_p, 2 * math.pi], atol=1e-9)
    np.testing.assert_allclose(traj.qd[-1, 0], 0.0, atol=1e-8)
    # θ is ignorable: p_θ = m r² θ̇ is conserved.
    p_theta = traj.momenta[:, 1]
    np.testing.assert_allclose(p_theta, m * r_p * v_p, rtol=1e-11)
    # Orbit equation r(θ) = a(1 − e²)/(1 + e cos θ).
    r_exact = a * (1 - e**2) / (1 + e * jnp.cos(traj.q[:, 1]))
    np.testing.assert_allclose(traj.q[:, 0], r_exact, atol=1e-9)


def charged_particle(q, qd, args):
    """L = ½ m |v|² + e v·A with A = ½ B (−y, x): uniform field B along z."""
    m, e, b = args["m"], args["e"], args["B"]
    x, y = q
    vector_potential = 0.5 * b * jnp.array([-y, x])
    return 0.5 * m * jnp.dot(qd, qd) + e * jnp.dot(qd, vector_potential)


def test_charged_particle_in_magnetic_field_gyrates():
    args = {"m": 2.0, "e": 1.5, "B": 4.0}
    v = 0.8
    omega = args["e"] * args["B"] / args["m"]  # cyclotron frequency eB/m
    radius = args["m"] * v / (args["e"] * args["B"])  # m v / (e B)
    ts = jnp.linspace(0.0, 3.0, 61)
    traj = jl.simulate(jl.System(charged_particle), [0.0, 0.0], [v, 0.0], ts, args=args, **TIGHT)
    # Force e v × B on v = (v, 0) with B along +z points to −y: centre at (0, −R), clockwise.
    np.testing.assert_allclose(traj.q[:, 0], radius * jnp.sin(omega * ts), atol=1e-10)
    np.testing.assert_allclose(traj.q[:, 1], -radius * (1 - jnp.cos(omega * ts)), atol=1e-10)
    # The velocity-dependent potential does no work: kinetic energy is conserved.
    np.testing.assert_allclose(traj.energy, 0.5 * args["m"] * v**2, rtol=1e-11)


def rim_pendulum(q, qd, t, args):
    """Pendulum hung from a point moving on a rim of radius a rotating at ω in the vertical plane."""
    a, w, l, g = args["a"], args["w"], args["l"], args["g"]
    th, thd = q[0], qd[0]
    y = a * jnp.sin(w * t) - l * jnp.cos(th)
    xd = -a * w * jnp.sin(w * t) + l * jnp.cos(th) * thd
    yd = a * w * jnp.cos(w * t) + l * jnp.sin(th) * thd
    return 0.5 * (xd**2 + yd**2) - g * y


def test_time_dependent_lagrangian_matches_hand_derived_equation():
    args = {"a": 0.3, "w": 2.5, "l": 1.2, "g": 9.81}
    ts = jnp.linspace(0.0, 5.0, 51)
    traj = jl.simulate(jl.System(rim_pendulum), [0.4], [0.0], ts, args=args, **TIGHT)

    def hand(t, y, a):
        th, thd = y
        # θ̈ = −(g/l) sin θ + (a ω²/l) cos(θ − ω t)
        return thd, -a["g"] / a["l"] * jnp.sin(th) + a["a"] * a["w"] ** 2 / a["l"] * jnp.cos(th - a["w"] * t)

    ref = diffrax.diffeqsolve(
        diffrax.ODETerm(hand),
        diffrax.Tsit5(),
        0.0,
        5.0,
        None,
        (jnp.array(0.4), jnp.array(0.0)),
        args,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=1e-12, atol=1e-12),
        max_steps=100_000,
    )
    np.testing.assert_allclose(traj.q[:, 0], ref.ys[0], atol=1e-9)
    np.testing.assert_allclose(traj.qd[:, 0], ref.ys[1], atol=1e-9)


def test_default_solver_runs_without_options():
    traj = jl.simulate(jl.System(harmonic), [1.0], [0.0], jnp.linspace(0, 1, 5), args={"m": 1.0, "k": 1.0})
    np.testing.assert_allclose(traj.q[:, 0], jnp.cos(jnp.linspace(0, 1, 5)), atol=1e-9)
    assert traj.stats["num_steps"] > 0


def test_diffrax_options_pass_through():
    ts = jnp.linspace(0.0, 1.0, 5)
    traj = jl.simulate(
        jl.System(harmonic),
        [1.0],
        [0.0],
        t0=0.0,
        t1=1.0,
        args={"m": 1.0, "k": 1.0},
        solver=diffrax.Dopri8(),
        stepsize_controller=diffrax.ConstantStepSize(),
        dt0=0.01,
        saveat=diffrax.SaveAt(ts=ts),
        max_steps=200,
    )
    assert int(traj.stats["num_steps"]) == 100
    np.testing.assert_allclose(traj.q[:, 0], jnp.cos(ts), atol=1e-12)
    with pytest.raises(Exception, match="max_steps"):
        jl.simulate(
            jl.System(harmonic),
            [1.0],
            [0.0],
            ts,
            args={"m": 1.0, "k": 1.0},
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=0.01,
            max_steps=10,
        )
