"""Unconstrained simulation against closed forms (core issue)."""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
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


# ------------------------------------------------------------------ option objects (Checks, Events)
def circle(q, qd, args):
    return 0.5 * (qd @ qd) - args["g"] * q[1]


def on_circle(q, args):
    return jnp.array([q @ q - 1.0])


CIRCLE = jl.System(circle, holonomic=on_circle)
CIRCLE_ARGS = {"g": 9.81}
CIRCLE_Q0 = jnp.array([0.6, -0.8])


def test_default_option_objects_are_the_old_defaults():
    ts = jnp.linspace(0.0, 1.0, 6)
    # Constrained: the default projects (jl.Projection()), checks everything, has no events.
    default = jl.simulate(CIRCLE, CIRCLE_Q0, jnp.zeros(2), ts, args=CIRCLE_ARGS)
    explicit = jl.simulate(
        CIRCLE,
        CIRCLE_Q0,
        jnp.zeros(2),
        ts,
        args=CIRCLE_ARGS,
        projection=jl.Projection(),
        checks=jl.Checks(initial_state=True, times=True, constraint_tolerance=None),
        events=jl.Events(),
    )
    np.testing.assert_array_equal(default.q, explicit.q)
    np.testing.assert_array_equal(default.qd, explicit.qd)
    assert default.events is None and default.active is None
    unprojected = jl.simulate(CIRCLE, CIRCLE_Q0, jnp.zeros(2), ts, args=CIRCLE_ARGS, projection=None)
    assert not np.array_equal(default.q, unprojected.q)
    np.testing.assert_allclose(default.q, unprojected.q, atol=1e-8)
    # Unconstrained: the projection is ignored, as "auto" did.
    args = {"m": 1.0, "k": 1.0}
    plain = jl.simulate(jl.System(harmonic), [1.0], [0.0], ts, args=args, projection=None)
    projected = jl.simulate(jl.System(harmonic), [1.0], [0.0], ts, args=args, projection=jl.Projection())
    np.testing.assert_array_equal(plain.q, projected.q)
    # The defaults of the Modules themselves.
    assert jl.Checks() == jl.Checks(initial_state=True, times=True, constraint_tolerance=None)
    events = jl.Events()
    assert events.conditions == () and events.max_segments == 8
    assert isinstance(events.root_finder, optx.Newton)
    assert events.root_finder.rtol == events.root_finder.atol == 1e-13


def test_string_projection_is_a_type_error():
    for projection in ("auto", "none"):
        with pytest.raises(TypeError, match=r"projection must be jl\.Projection\(\) or None"):
            jl.simulate(
                CIRCLE,
                CIRCLE_Q0,
                jnp.zeros(2),
                jnp.linspace(0.0, 1.0, 3),
                args=CIRCLE_ARGS,
                projection=projection,
            )


def test_wrong_events_or_checks_are_type_errors():
    ts = jnp.linspace(0.0, 1.0, 3)
    event = jl.Event(lambda q, qd: q[0])
    run = lambda **kw: jl.simulate(jl.System(pendulum), [0.3], [0.0], ts, args={"g": 9.81, "l": 1.0}, **kw)
    with pytest.raises(
        TypeError, match=r"events must be a jl\.Events, a jl\.Event or a sequence of jl\.Event"
    ):
        run(events="crossing")
    with pytest.raises(TypeError, match=r"events must be a jl\.Events.*holding int"):
        run(events=[event, 3])
    with pytest.raises(TypeError, match=r"events must be a jl\.Events"):
        run(events=lambda q, qd: q[0])
    with pytest.raises(TypeError, match=r"checks must be a jl\.Checks"):
        run(checks=False)
    with pytest.raises(TypeError, match=r"separate arguments: jl\.Events\(\*conditions\)"):
        jl.Events([event])
    with pytest.raises(TypeError, match=r"jl\.Events takes jl\.Event conditions"):
        jl.Events(lambda q, qd: q[0])
    with pytest.raises(TypeError, match="unexpected keyword"):
        jl.Events(conditions=(event,))
    with pytest.raises(ValueError, match="max_segments must be a positive integer"):
        jl.Events(event, max_segments=0)
    with pytest.raises(TypeError, match="root_finder must be an optimistix root finder"):
        jl.Events(event, root_finder=1e-13)
    with pytest.raises(ValueError, match="constraint_tolerance must be positive"):
        jl.Checks(constraint_tolerance=0.0)
    # The removed keywords are not silently accepted.
    for removed in (
        {"max_segments": 3},
        {"event_root_finder": optx.Newton(rtol=1e-8, atol=1e-8)},
        {"check_initial_state": False},
        {"check_times": False},
        {"constraint_tolerance": 1e-6},
    ):
        with pytest.raises(TypeError, match="unexpected keyword"):
            run(**removed)


def test_events_object_plain_event_and_list_agree():
    ts = jnp.linspace(0.0, 1.0, 6)
    crossing = jl.Event(lambda q, qd: q[0], terminal=False)
    run = lambda events: jl.simulate(
        jl.System(pendulum), [0.3], [0.0], ts, args={"g": 9.81, "l": 1.0}, events=events
    )
    single, listed, wrapped = run(crossing), run([crossing]), run(jl.Events(crossing))
    for other in (listed, wrapped):
        np.testing.assert_array_equal(single.q, other.q)
        np.testing.assert_array_equal(single.events.time, other.events.time)
    assert single.events.time.shape == (8,)  # the default max_segments
    # The pendulum crosses q = 0 at a quarter period, √(l/g) K(sin(θ0/2)); then the end time.
    assert single.events.kinds() == ["user", "end"]  # the real entries, no padding
    quarter = math.sqrt(1.0 / 9.81) * complete_elliptic_k(math.sin(0.15))
    np.testing.assert_allclose(single.events.time[0], quarter, rtol=1e-7)
    # max_segments and root_finder are taken from the Events.
    short = run(jl.Events(crossing, max_segments=2, root_finder=optx.Newton(rtol=1e-13, atol=1e-13)))
    assert short.events.time.shape == (2,)
    np.testing.assert_array_equal(short.events.time, single.events.time[:2])
    np.testing.assert_array_equal(short.q, single.q)
    with pytest.raises(jl.SimulationError, match=r"max_segments = 1 .*jl\.Events\(\.\.\., max_segments="):
        run(jl.Events(crossing, max_segments=1))


def test_checks_object_controls_the_initial_state_check():
    ts = jnp.linspace(0.0, 0.5, 3)
    off = jnp.array([0.6, -0.81])  # |q|² − 1 = 0.0161: off the circle
    with pytest.raises(ValueError, match="off the constraint manifold"):
        jl.simulate(CIRCLE, off, jnp.zeros(2), ts, args=CIRCLE_ARGS)
    # Skipped: the run starts from the given state (and the projection pulls it onto the circle).
    traj = jl.simulate(CIRCLE, off, jnp.zeros(2), ts, args=CIRCLE_ARGS, checks=jl.Checks(initial_state=False))
    np.testing.assert_allclose(jnp.sum(traj.q[1:] ** 2, axis=-1), 1.0, atol=1e-8)
    # A looser tolerance accepts the state; a tighter one refuses a nearly consistent one.
    jl.simulate(CIRCLE, off, jnp.zeros(2), ts, args=CIRCLE_ARGS, checks=jl.Checks(constraint_tolerance=0.1))
    near = CIRCLE_Q0 * (1.0 + 1e-9)
    jl.simulate(CIRCLE, near, jnp.zeros(2), ts, args=CIRCLE_ARGS)
    with pytest.raises(ValueError, match="beyond the tolerance 1e-12"):
        jl.simulate(
            CIRCLE, near, jnp.zeros(2), ts, args=CIRCLE_ARGS, checks=jl.Checks(constraint_tolerance=1e-12)
        )
    # Under jit (compiled check) too.
    with pytest.raises(Exception, match="off the constraint manifold"):
        jax.block_until_ready(
            jax.jit(lambda q: jl.simulate(CIRCLE, q, jnp.zeros(2), ts, args=CIRCLE_ARGS).q)(off)
        )
    skipped = jax.jit(
        lambda q: (
            jl.simulate(
                CIRCLE, q, jnp.zeros(2), ts, args=CIRCLE_ARGS, checks=jl.Checks(initial_state=False)
            ).q
        )
    )(off)
    np.testing.assert_allclose(skipped, traj.q, atol=1e-12)


def test_checks_times_false_compiles_no_check_of_traced_save_times():
    args = {"m": 1.0, "k": 1.0}

    def callbacks(times):
        checks = jl.Checks(initial_state=False, times=times)
        jaxpr = jax.make_jaxpr(
            lambda ts: jl.simulate(jl.System(harmonic), [1.0], [0.0], ts, args=args, checks=checks).q
        )(jnp.linspace(0.0, 1.0, 5))
        return str(jaxpr).count("callback")

    assert callbacks(True) > callbacks(False)
    with pytest.raises(Exception, match="strictly increasing"):
        jax.block_until_ready(
            jax.jit(lambda ts: jl.simulate(jl.System(harmonic), [1.0], [0.0], ts, args=args).q)(
                jnp.array([0.0, 0.5, 0.4])
            )
        )


def test_python_float_parameters_take_the_state_dtype():
    # A Python float in args is weakly typed: in a float32 run it is float32, so the user's
    # functions are not promoted to float64 (under the suite's strict promotion a float64
    # parameter against float32 coordinates would be an error). NumPy arrays keep their dtype.
    seen = []

    def pendulum(q, qd, args):
        seen.append(args["g"].dtype)
        return 0.5 * qd[0] ** 2 + args["g"] * jnp.cos(q[0])

    system = jl.System(pendulum)
    q0, qd0 = jnp.array([0.5], jnp.float32), jnp.zeros(1, jnp.float32)
    ts = jnp.linspace(0.0, 1.0, 3, dtype=jnp.float32)
    traj = jl.simulate(system, q0, qd0, ts, args={"g": 9.81})
    batch = jl.simulate_batch(system, q0[None], qd0[None], ts, args={"g": 9.81}, method=jl.Ensemble())
    assert traj.q.dtype == batch.q.dtype == jnp.float32
    assert set(seen) == {jnp.dtype(jnp.float32)}
    np.testing.assert_allclose(traj.q, batch.q[0], atol=1e-5)
    seen.clear()
    jl.simulate(system, q0.astype(jnp.float64), qd0.astype(jnp.float64), ts, args={"g": 9.81})
    assert set(seen) == {jnp.dtype(jnp.float64)}
