"""Unilateral constraints and events: release, free flight, contact, user events, gradients."""

import math

import diffrax
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


def test_user_event_in_the_same_step_as_a_release():
    # θ passes marks 1e-3 rad before and after the release angle, cos θr = (2/3) cos θ0.
    # Before, a user crossing in the solver step that also held the release was lost (the
    # release was located first and the condition's sign change went unseen); just after a
    # release the gap (~0, growing quadratically) could be taken for a contact.
    theta0 = 0.1
    theta_release = math.acos(2.0 / 3.0 * math.cos(theta0))
    marks = [theta_release - 1e-3, theta_release + 1e-3]
    events = [jl.Event(lambda q, qd, m=m: q[1] - m, terminal=False) for m in marks]
    traj = jl.simulate(SPHERE, jnp.array([R, theta0]), jnp.zeros(2), TS, args=ARGS, events=events)
    log = traj.events
    assert log.kinds() == ["user", "release", "user", "end"]
    np.testing.assert_array_equal(log.index[:3], [0, 0, 1])
    np.testing.assert_allclose(log.q[[0, 2], 1], marks, atol=1e-12)  # the root find's tolerance
    np.testing.assert_allclose(math.cos(log.q[1, 1]), 2.0 / 3.0 * math.cos(theta0), atol=1e-9)


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


# ----------------------------------------------------------------------------- crossing semantics
# The harmonic oscillator q̈ = −q: q = cos(t + φ) from (cos φ, −sin φ), crossings in closed form.
OSCILLATOR = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2)
TS10 = jnp.linspace(0.0, 10.0, 11)
# Recorded conditions: one per direction, two that cross at the same instant, one that crosses
# 1e-3 before them (within one solver step).
DIRECTED = jl.Events(
    jl.Event(lambda q, qd: q[0] - 0.5, terminal=False, direction=True),  # up through 0.5
    jl.Event(lambda q, qd: q[0] + 0.5, terminal=False, direction=False),  # down through −0.5
    jl.Event(lambda q, qd: q[0], terminal=False),  # either way through 0
    jl.Event(lambda q, qd: 2 * q[0], terminal=False),  # the same instants
    jl.Event(lambda q, qd: q[0] - 1e-3, terminal=False),  # 1e-3 away
    max_segments=16,
)
PI = math.pi
NEAR = math.acos(1e-3)
# The crossings of q = cos(t + φ) for t + φ in (0, 10]: each recorded exactly once, none in the
# direction a condition ignores (cos t = 0.5 is crossed downwards at π/3, not recorded).
DIRECTED_EXPECTED = [
    [5 * PI / 3],
    [2 * PI / 3, 2 * PI + 2 * PI / 3],
    [PI / 2, 3 * PI / 2, 5 * PI / 2],
    [PI / 2, 3 * PI / 2, 5 * PI / 2],
    [NEAR, 2 * PI - NEAR, 2 * PI + NEAR],
]


def directed(phi):
    q0, qd0 = jnp.array([jnp.cos(phi)]), jnp.array([-jnp.sin(phi)])
    return jl.simulate(OSCILLATOR, q0, qd0, TS10, events=DIRECTED)


def check_directed(log, phi):
    kind, index, time = (np.asarray(x) for x in (log.kind, log.index, log.time))
    assert list(kind[:13]) == [3] * 12 + [0] and int(log.count) == 12
    assert np.all(np.diff(time[:13]) >= 0)  # in the order they happened
    for j, expected in enumerate(DIRECTED_EXPECTED):
        # Root find at 1e-13 on a solution accurate to ~1e-10 (PIDController 1e-10).
        np.testing.assert_allclose(time[:12][index[:12] == j], np.array(expected) - phi, atol=1e-9)


def test_directions_and_simultaneous_crossings_eager_jit_vmap():
    # Before: direction=True/False failed with "maximum number of steps in the nonlinear
    # solver" at the second crossing (the condition was pinned to the wrong side after the
    # first); a crossing could be recorded twice; of two conditions crossing in one solver
    # step only the first in list order was located (the other was lost, or recorded again
    # and again at that time until max_segments ran out).
    traj = directed(0.0)
    check_directed(traj.events, 0.0)
    assert traj.events.kinds() == ["user"] * 12 + ["end"]
    # The state after a recorded event continues the motion: saves match cos t.
    np.testing.assert_allclose(traj.q[:, 0], jnp.cos(TS10), atol=1e-9)
    # Statistics: the segments' diffrax statistics summed. 16 segments ran: 12 events, the
    # end, and the 3 crossings the directional conditions ignore (not in the log).
    stats = traj.stats
    assert int(stats["num_segments"]) == 16
    assert int(stats["num_steps"]) == int(stats["num_accepted_steps"]) + int(stats["num_rejected_steps"])
    # Compiled and batched (one program); φ shifts every crossing to t − φ.
    phis = jnp.array([0.0, 0.3])
    batched = jax.jit(jax.vmap(directed))(phis)
    np.testing.assert_allclose(batched.events.time[0], traj.events.time, atol=1e-12)
    check_directed(jax.tree.map(lambda x: x[1], batched.events), 0.3)
    assert batched.events.kinds() == [["user"] * 12 + ["end"]] * 2
    assert batched.stats["num_segments"].shape == (2,)


def test_condition_zero_at_t0_is_not_a_crossing():
    # q = v sin t: q[0] is exactly 0 at t0. Before: every segment fired again at t0 ("needed
    # more than max_segments"). Now t0 is not a crossing: whichever way q leaves 0 (the sign
    # of ċ = v decides), the first event is at π. At rest at the equilibrium (v = 0) the
    # condition stays exactly 0 and never crosses. Eager, then compiled and batched.
    event = jl.Events(jl.Event(lambda q, qd: q[0], terminal=False), max_segments=4)
    run = lambda v: jl.simulate(OSCILLATOR, jnp.zeros(1), jnp.array([v]), TS10, events=event)  # noqa: E731
    log = run(1.0).events
    assert log.kinds() == ["user", "user", "user", "end"]
    np.testing.assert_allclose(log.time[:3], [PI, 2 * PI, 3 * PI], atol=1e-9)
    batched = jax.jit(jax.vmap(run))(jnp.array([1.0, -1.0, 0.0]))
    assert batched.events.kinds() == [["user", "user", "user", "end"]] * 2 + [["end"]]
    np.testing.assert_allclose(batched.events.time[:2, :3], [[PI, 2 * PI, 3 * PI]] * 2, atol=1e-9)
    np.testing.assert_allclose(batched.q[2], 0.0, atol=0)


def test_condition_zero_to_second_order_at_t0():
    # q̈ = 1 − q from rest at 0: q = 1 − cos t. c = q − t²/4 = t⁴·(…) − … has c = ċ = 0 and
    # c̈ = 1/2 at t0: it starts positive (the second derivative decides) and first crosses at
    # the root of 1 − cos t = t²/4. Terminal: it stops there.
    system = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * (q[0] - 1.0) ** 2)
    event = jl.Event(lambda q, qd, t: q[0] - t**2 / 4)
    traj = jl.simulate(system, jnp.zeros(1), jnp.zeros(1), jnp.linspace(0.0, 4.0, 5), events=event)
    root = 2.5  # Newton on 1 − cos t − t²/4 (its only positive root)
    for _ in range(50):
        root -= (1 - math.cos(root) - root**2 / 4) / (math.sin(root) - root / 2)
    assert traj.events.kinds() == ["user"]
    np.testing.assert_allclose(traj.events.time[0], root, atol=1e-9)


def pendulum(q, qd):
    return 0.5 * qd[0] ** 2 + G * jnp.cos(q[0])  # unit length: θ̈ = −g sin θ


def pendulum_period(theta0):
    """T = 4 K(sin(θ0/2)) / √g, K by the arithmetic-geometric mean."""
    a, b = 1.0, math.sqrt(1.0 - math.sin(theta0 / 2) ** 2)
    for _ in range(10):
        a, b = (a + b) / 2, math.sqrt(a * b)
    return 4 * (math.pi / (2 * a)) / math.sqrt(G)


def test_pendulum_velocity_events_recorded_once():
    # θ̇ starts at exactly 0 (released at rest) and turns negative; downward crossings of θ̇
    # are the return to the start at T, 2T. Before: the crossing at T was recorded twice.
    theta0 = 0.3
    period = pendulum_period(theta0)
    # 5 segments: the 2 events, the 2 upward crossings (not recorded) and the end.
    event = jl.Events(jl.Event(lambda q, qd: qd[0], terminal=False, direction=False), max_segments=5)
    ts = jnp.linspace(0.0, 2.2 * period, 5)
    log = jl.simulate(jl.System(pendulum), jnp.array([theta0]), jnp.zeros(1), ts, events=event).events
    assert log.kinds() == ["user", "user", "end"]
    np.testing.assert_allclose(log.time[:2], [period, 2 * period], rtol=1e-9)


def test_float32_terminal_event_on_a_pendulum():
    # Before: in float32 the root finder (Newton, rtol = atol = 1e-13, below float32 round-off)
    # never stopped: "maximum number of steps in the nonlinear solver". The default root
    # finder's tolerances now follow the dtype; float64 keeps 1e-13.
    theta0 = 0.3
    quarter = pendulum_period(theta0) / 4  # θ first reaches 0 at T/4
    with jax.enable_x64(False):
        traj = jl.simulate(
            jl.System(pendulum),
            jnp.array([theta0]),
            jnp.zeros(1),
            jnp.linspace(0.0, 1.0, 3),
            events=jl.Event(lambda q, qd: q[0]),
        )
        assert traj.events.time.dtype == jnp.float32
        assert traj.events.kinds() == ["user"]
        # float32: solver rtol 1.2e-5 (100 ulps); measured relative error 5.3e-6.
        np.testing.assert_allclose(float(traj.events.time[0]), quarter, rtol=2e-5)
    from jaxlag._events import root_finder_for

    default = jl.Events().root_finder
    # The default keeps its tolerances in float64 (1e-13); it is run as ResolvedNewton, which
    # also stops at the resolution of t (tests/test_impacts.py).
    assert root_finder_for(default, jnp.float64).atol == root_finder_for(default, jnp.float64).rtol == 1e-13
    assert root_finder_for(default, jnp.float32).atol == pytest.approx(2.0**-11.5)
    custom = jl.Events(root_finder=__import__("optimistix").Newton(rtol=1e-3, atol=1e-3)).root_finder
    assert root_finder_for(custom, jnp.float32) is custom


def test_stats_and_kinds_without_padding():
    # A terminal event that never fires: one segment, the same steps as the plain solve. (A
    # segment is solved in the run's time, a plain solve on the unit interval, whose first step
    # differs: compare with a plain solve in real time, which a ClipStepSizeController gets.)
    never = jl.Event(lambda q, qd: q[0] - 2.0)
    q0, qd0 = jnp.array([1.0]), jnp.zeros(1)
    with_event = jl.simulate(OSCILLATOR, q0, qd0, TS10, events=never)
    real_time = diffrax.ClipStepSizeController(diffrax.PIDController(rtol=1e-10, atol=1e-10))
    plain = jl.simulate(OSCILLATOR, q0, qd0, TS10, stepsize_controller=real_time)
    for key in ("num_steps", "num_accepted_steps", "num_rejected_steps", "max_steps"):
        assert int(with_event.stats[key]) == int(plain.stats[key]), key
    assert int(with_event.stats["num_segments"]) == 1
    assert with_event.events.kinds() == ["end"]
    np.testing.assert_allclose(with_event.q, plain.q, atol=1e-12)


def test_too_many_segments_message_says_what_to_pass():
    # q[0] = cos t crosses 0 at π/2, 3π/2, 5π/2 in [0, 10]: 4 segments with the end.
    event = jl.Event(lambda q, qd: q[0], terminal=False)
    run = lambda m, **kw: jl.simulate(  # noqa: E731
        OSCILLATOR, jnp.ones(1), jnp.zeros(1), TS10, events=jl.Events(event, max_segments=m), **kw
    )
    with pytest.raises(jl.SimulationError) as info:
        run(2)
    text = str(info.value)
    # After 2 segments it reached 3π/2 = 47.1% of the interval: ⌈2/0.471⌉ + 1 = 6 needed.
    assert "needed more than max_segments = 2" in text and "t = 4.71238898" in text
    assert "about 6 segments are needed" in text and "max_segments=8" in text
    # throw=False: the record says what happened; the log holds the two events it found.
    kept = run(2, throw=False)
    assert int(kept.failure.code) == 4 and kept.events.kinds() == ["user", "user"]
    assert int(kept.stats["num_segments"]) == 2
    # Compiled: the static message.
    with pytest.raises(Exception, match="max_segments"):
        jax.jit(
            lambda q0: (
                jl.simulate(OSCILLATOR, q0, jnp.zeros(1), TS10, events=jl.Events(event, max_segments=2)).q
            )
        )(jnp.ones(1))


def test_event_kinds_are_an_enumeration_compared_by_name():
    # The integer values of EventLog.kind are unchanged; the names are those of kinds(). IMPACT
    # (a rebound, restitution e > 0: tests/test_impacts.py) came after them, as 6.
    assert [int(k) for k in jl.EventKind] == [-2, -1, 0, 1, 2, 3, 4, 5, 6]
    assert jl.EventKind.CONTACT.label == "contact" and jl.EventKind.IMPACT.label == "impact"
    kinds = jnp.asarray([jl.EventKind.RELEASE, jl.EventKind.END, jl.EventKind.NONE], jnp.int32)
    assert bool(jax.jit(lambda k: k[0] == jl.EventKind.RELEASE)(kinds))
    log = jl.EventLog(
        time=jnp.zeros(3),
        kind=kinds,
        index=jnp.zeros(3, jnp.int32),
        q=jnp.zeros((3, 1)),
        qd=jnp.zeros((3, 1)),
        active=jnp.zeros((3, 0), bool),
        impulses=jnp.zeros((3, 0)),
        count=jnp.asarray(1, jnp.int32),
    )
    assert log.kinds() == ["release", "end"]
