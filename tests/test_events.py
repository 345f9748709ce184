"""Unilateral constraints and events: release, free flight, contact, user events, gradients."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl

G, R = 9.81, 1.0


def sphere_lagrangian(q, qd, args):
    r, th = q  # θ from the top
    rd, thd = qd
    return 0.5 * (rd**2 + r**2 * thd**2) - args["g"] * r * jnp.cos(th)


def outside_sphere(q, args):
    return jnp.array([q[0] - args["R"]])  # r − R ≥ 0, λ ≥ 0 is the outward normal force


SPHERE = jl.System(sphere_lagrangian, holonomic=outside_sphere, unilateral=0)
ARGS = {"g": G, "R": R}
TS = jnp.linspace(0.0, 1.6, 33)


def release(theta0, g=G, thetad0=0.0):
    return jl.simulate(SPHERE, jnp.array([R, theta0]), jnp.array([0.0, thetad0]), TS, args={"g": g, "R": R})


def test_particle_leaves_sphere_at_two_thirds_cos_theta0():
    theta0 = 0.1
    traj = release(theta0)
    log = traj.events
    assert log.kinds()[:2] == ["release", "end"]
    assert int(log.count) == 1
    theta_release = log.q[0, 1]
    # Exact for any start from rest: energy gives R θ̇² = 2g(cos θ0 − cos θ), λ = 0 gives
    # cos θ = (2/3) cos θ0. The event root find runs at 1e-13 on a solution accurate to ~1e-10.
    assert abs(math.cos(theta_release) - 2.0 / 3.0 * math.cos(theta0)) < 1e-9
    # Multiplier positive before, exactly zero (inactive) after; activity recorded per save.
    on = traj.active[:, 0]
    assert bool(on[0]) and not bool(on[-1])
    assert jnp.all(traj.multipliers[on, 0] > 0)
    assert jnp.all(traj.multipliers[~on, 0] == 0)


def test_free_flight_after_release_is_the_parabola():
    traj = release(0.1)
    t_e = traj.events.time[0]
    r_e, th_e = traj.events.q[0]
    rd_e, thd_e = traj.events.qd[0]
    x_e, y_e = r_e * jnp.sin(th_e), r_e * jnp.cos(th_e)
    vx = rd_e * jnp.sin(th_e) + r_e * jnp.cos(th_e) * thd_e
    vy = rd_e * jnp.cos(th_e) - r_e * jnp.sin(th_e) * thd_e
    after = TS > t_e
    dt = TS[after] - t_e
    r, th = traj.q[after, 0], traj.q[after, 1]
    # Free fall from the release state; the solver tolerance (1e-10) bounds the error.
    np.testing.assert_allclose(r * jnp.sin(th), x_e + vx * dt, atol=1e-9)
    np.testing.assert_allclose(r * jnp.cos(th), y_e + vy * dt - 0.5 * G * dt**2, atol=1e-9)
    # Released particles move away from the sphere.
    assert jnp.all(r > R)


def test_stitched_trajectory_is_continuous_and_conserves_energy():
    traj = release(0.3)
    # No impact happens, so the energy function is conserved across the release.
    np.testing.assert_allclose(traj.energy, traj.energy[0], atol=1e-9)
    # Position and velocity continuity at the switch: the state just after equals the
    # state on the constrained branch (no jump at a release).
    t_e = traj.events.time[0]
    i = int(jnp.searchsorted(TS, t_e))
    dense = jl.simulate(
        SPHERE,
        traj.q[i - 1],
        traj.qd[i - 1],
        jnp.array([TS[i - 1], t_e]),
        args=ARGS,
        events=jl.Events(max_segments=1),
        throw=False,
    )
    np.testing.assert_allclose(dense.q[-1], traj.events.q[0], atol=1e-9)
    np.testing.assert_allclose(dense.qd[-1], traj.events.qd[0], atol=1e-8)


def string_lagrangian(q, qd, args):
    r, th = q  # θ from the downward vertical
    rd, thd = qd
    return 0.5 * (rd**2 + r**2 * thd**2) + args["g"] * r * jnp.cos(th)


def string(q, args):
    return jnp.array([args["l"] - q[0]])  # l − r ≥ 0; λ ≥ 0 is the tension


def test_string_pendulum_goes_slack_then_taut_again():
    g, l = 9.81, 1.0
    v0 = math.sqrt(3.5 * g * l)  # between √(2gl) and √(5gl): slack above the horizontal
    system = jl.System(string_lagrangian, holonomic=string, unilateral=0)
    ts = jnp.linspace(0.0, 2.0, 201)
    traj = jl.simulate(system, jnp.array([l, 0.0]), jnp.array([0.0, v0 / l]), ts, args={"g": g, "l": l})
    kinds = traj.events.kinds()
    assert kinds[:2] == ["release", "contact"], kinds
    # Tension T = m v²/l + m g cos θ with v² = v0² − 2gl(1 − cos θ) vanishes at
    # cos θ = (2gl − v0²)/(3gl).
    theta_slack = traj.events.q[0, 1]
    assert abs(math.cos(theta_slack) - (2 * g * l - v0**2) / (3 * g * l)) < 1e-9
    # Slack: r < l in free flight; taut again at the contact, with a plastic jerk (ṙ⁺ = 0).
    t_slack, t_taut = traj.events.time[0], traj.events.time[1]
    flying = (ts > t_slack) & (ts < t_taut)
    assert jnp.any(flying) and jnp.all(traj.q[flying, 0] < l)
    np.testing.assert_allclose(traj.events.q[1, 0], l, atol=1e-12)
    np.testing.assert_allclose(traj.events.qd[1, 0], 0.0, atol=1e-12)
    # The impact dissipates energy: h after the jerk is lower than before.
    h = traj.energy
    assert h[-1] < h[0] - 1e-3


def test_user_events_terminal_and_recorded():
    def angle_passes(q, qd):
        return q[1] - 0.5  # θ crosses 0.5 rad (recorded, not terminal)

    def force_limit(q, qd, multipliers):
        return multipliers[0] - 0.5 * G  # normal force drops below half the weight: stop

    traj = jl.simulate(
        SPHERE,
        jnp.array([R, 0.1]),
        jnp.zeros(2),
        TS,
        args=ARGS,
        events=[jl.Event(angle_passes, terminal=False), jl.Event(force_limit, direction=False)],
    )
    kinds = traj.events.kinds()
    assert kinds[:2] == ["user", "user"], kinds
    np.testing.assert_array_equal(traj.events.index[:2], [0, 1])
    np.testing.assert_allclose(traj.events.q[0, 1], 0.5, atol=1e-12)
    # λ = m g (3 cos θ − 2 cos θ0) = g/2 at the terminal event.
    cos_stop = (0.5 + 2 * math.cos(0.1)) / 3
    np.testing.assert_allclose(math.cos(traj.events.q[1, 1]), cos_stop, atol=1e-10)
    # After a terminal event the remaining saves are inf (diffrax's convention).
    stopped = TS > traj.events.time[1]
    assert jnp.all(jnp.isinf(traj.q[stopped])) and jnp.all(jnp.isfinite(traj.q[~stopped]))


def test_release_time_gradient_wrt_g():
    def t_release(g):
        return release(0.2, g=g).events.time[0]

    g = 9.81
    grad = jax.grad(t_release)(g)
    # Dimensional analysis: t_release = τ(θ0) √(R/g), so dt/dg = −t/(2g) exactly.
    np.testing.assert_allclose(grad, -t_release(g) / (2 * g), rtol=1e-7)
    h = 1e-4
    fd = (t_release(g + h) - t_release(g - h)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_release_angle_gradient_wrt_initial_angle():
    def theta_release(theta0):
        return release(theta0).events.q[0, 1]

    theta0 = 0.2
    grad = jax.grad(theta_release)(theta0)
    # cos θr = (2/3) cos θ0  ⇒  dθr/dθ0 = (2/3) sin θ0 / sin θr.
    expected = 2.0 / 3.0 * math.sin(theta0) / math.sin(theta_release(theta0))
    # The discrete solution's derivative matches the exact one to the solver tolerance (1e-10)
    # amplified by the unstable growth away from the top (measured 1.7e-7 relative).
    np.testing.assert_allclose(grad, expected, rtol=1e-6)
    h = 1e-5
    fd = (theta_release(theta0 + h) - theta_release(theta0 - h)) / (2 * h)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_batch_of_256_releases_matches_the_loop():
    thetas = jnp.linspace(0.05, 0.6, 256)
    batched = jax.vmap(release)(thetas)
    assert batched.q.shape == (256, 33, 2)
    expected = jnp.arccos(2.0 / 3.0 * jnp.cos(thetas))
    np.testing.assert_allclose(batched.events.q[:, 0, 1], expected, atol=1e-8)
    for i in range(0, 256, 51):  # the loop, on a spread of members (each call is the same program)
        single = release(thetas[i])
        np.testing.assert_allclose(batched.q[i], single.q, atol=1e-12)
        np.testing.assert_allclose(batched.events.time[i], single.events.time, atol=1e-12)


def test_wrong_sign_multiplier_at_start_is_an_error():
    with pytest.raises(ValueError, match="wrong sign"):
        release(0.3, thetad0=5.0)  # so fast that holding it on the sphere would need a pull


def test_too_few_segments_is_an_error():
    system = jl.System(string_lagrangian, holonomic=string, unilateral=0)
    with pytest.raises(Exception, match="max_segments"):
        jl.simulate(
            system,
            jnp.array([1.0, 0.0]),
            jnp.array([0.0, math.sqrt(3.5 * 9.81)]),
            jnp.linspace(0.0, 2.0, 21),
            args={"g": 9.81, "l": 1.0},
            events=jl.Events(max_segments=1),
        )


def rim_loop(q, qd, args):
    """A car on the inside of a vertical loop of radius ρ, polar (r, θ), θ from the bottom."""
    r, th = q
    rd, thd = qd
    return 0.5 * (rd**2 + r**2 * thd**2) + args["g"] * r * jnp.cos(th)


def test_force_limit_event_on_a_loop():
    # Inside a loop the track pushes inward: f = ρ − r ≥ 0 with λ = m v²/ρ + m g cos θ ≥ 0.
    system = jl.System(rim_loop, holonomic=lambda q, args: jnp.array([args["rho"] - q[0]]), unilateral=0)
    g, rho, v0 = 9.81, 1.0, 6.0
    limit = 3.0 * g  # "3 g" on the rider
    ts = jnp.linspace(0.0, 0.5, 11)
    # Entering at the bottom the load is v0²/ρ + g = 45.8 > 3g; it drops as the car climbs:
    # v² = v0² − 2gρ(1 − cos θ) gives λ = v0²/ρ − 2g + 3g cos θ, equal to the limit at
    # cos θ = (limit − v0²/ρ + 2g)/(3g).
    traj = jl.simulate(
        system,
        jnp.array([rho, 0.0]),
        jnp.array([0.0, v0 / rho]),
        ts,
        args={"g": g, "rho": rho},
        events=[jl.multiplier_limit(0, limit, below=True)],
    )
    assert traj.events.kinds()[0] == "user"
    cos_theta = (limit - v0**2 / rho + 2 * g) / (3 * g)
    np.testing.assert_allclose(math.cos(traj.events.q[0, 1]), cos_theta, atol=1e-10)
