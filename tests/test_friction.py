"""Coulomb friction as a stick–slip element (jl.Coulomb): closed forms, jit, vmap, grad.

Compile-time budget: one compiled program, jit(vmap(jacrev)), serves every physics check. One
system, a block of mass M on an incline of angle θ (θ = 0: a flat floor) pushed along the
slope by c·t + A sin 2t; its members: launched up a ramp with μ > tan θ (stops and sticks),
with μ < tan θ (stops and slides back), on a floor pushed by a growing force (sticks, then
slips), on a floor pushed to and fro (slip, stick, slip in the other direction), and two
members at v0 ± h for the finite differences. θ, c, A and μ are array leaves, so the members
differ only in values.
"""

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl

G, M = 9.81, 2.0
THETA = math.radians(30.0)  # tan θ = 0.577
V0, STEP = 3.0, 1e-4
PUSH = 20.0  # floor: c [N/s], sticking breaks at t_s = μ M g / c
SHAKE = 10.0  # floor: A [N] of A sin 2t, above μ M g = 5.9 for μ = 0.3
TS = jnp.linspace(0.0, 2.0, 41)
# (v0, μ, θ, c, A) per member
MEMBERS = np.array(
    [
        [V0, 0.8, THETA, 0.0, 0.0],  # μ > tan θ: stops and stays
        [V0, 0.3, THETA, 0.0, 0.0],  # μ < tan θ: stops and slides back
        [0.0, 0.5, 0.0, PUSH, 0.0],  # floor: stick, then slip
        [0.0, 0.3, 0.0, 0.0, SHAKE],  # floor, to and fro: slip, stick, slip back
        [V0 + STEP, 0.8, THETA, 0.0, 0.0],  # finite differences in v0
        [V0 - STEP, 0.8, THETA, 0.0, 0.0],
    ]
)
# A stuck block does not move: the controller's steps would grow past the to-and-fro push's
# switches (Coulomb's docstring); dtmax keeps them below its time scale.
CONTROLLER = diffrax.PIDController(rtol=1e-10, atol=1e-10, dtmax=0.1)


def lagrangian(q, qd):
    return 0.5 * M * (qd @ qd) - M * G * q[1]


def surface(q, args):  # the distance from the incline: f ≥ 0, λ_N ≥ 0 pushes
    th = args["theta"]
    return jnp.stack([-jnp.sin(th) * q[0] + jnp.cos(th) * q[1]])


def along(q, args):  # the position along the slope: τ̇ = v_t
    th = args["theta"]
    return jnp.cos(th) * q[0] + jnp.sin(th) * q[1]


def push(q, qd, t, args):
    th = args["theta"]
    return (args["c"] * t + args["A"] * jnp.sin(2.0 * t)) * jnp.stack([jnp.cos(th), jnp.sin(th)])


def first_switch(params):
    """(time of the first friction switch, τ there), and the run."""
    v0, mu, th, c, a = params
    system = jl.System(lagrangian, surface, forces=push, unilateral=0, friction=jl.Coulomb(0, along, mu))
    qd0 = v0 * jnp.stack([jnp.cos(th), jnp.sin(th)])
    args = {"theta": th, "c": c, "A": a}
    events = jl.Events(max_segments=4)
    traj = jl.simulate(
        system, jnp.zeros(2), qd0, TS, args=args, events=events, stepsize_controller=CONTROLLER
    )
    log = traj.events
    out = jnp.stack([log.time[0], along(log.q[0], args)])
    return out, (
        log.kind,
        log.time,
        traj.q,
        traj.qd,
        traj.friction_forces,
        traj.multipliers,
        traj.friction_modes,
    )


# One program: values and gradients of every member at once.
BATCH = jax.jit(jax.vmap(jax.jacrev(first_switch, has_aux=True)))


@pytest.fixture(scope="module")
def batch():
    jac, aux = BATCH(jnp.asarray(MEMBERS))
    kinds, times, q, qd, lam_t, lam, modes = (np.asarray(x) for x in aux)
    return dict(jac=np.asarray(jac), kinds=kinds, times=times, q=q, qd=qd, lam_t=lam_t, lam=lam, modes=modes)


def up_the_ramp(v0, mu, th=THETA):
    """Deceleration, stop time and stop distance of a block launched up at v0 (slipping, s = +1)."""
    a = G * (math.sin(th) + mu * math.cos(th))
    return a, v0 / a, v0**2 / (2 * a)


def tau(q, th=THETA):
    return math.cos(th) * q[..., 0] + math.sin(th) * q[..., 1]


def test_block_stops_on_ramp_and_stays_stopped(batch):
    _, t_stop, s_stop = up_the_ramp(V0, 0.8)
    kinds, times = batch["kinds"][0], batch["times"][0]
    assert list(kinds[:2]) == [4, 0]  # "stick", then the end
    # The stop is a root of s·v_t on Tsit5's dense output (quadratic in t here, exact) found
    # by Newton to 1e-13: measured error 1e-16.
    assert abs(times[0] - t_stop) < 1e-12
    after = np.asarray(TS) > t_stop
    q, qd = batch["q"][0], batch["qd"][0]
    # Stuck: the stick row keeps v_t = 0 (projected to 0 at the stop; ẍ = 0 to round-off).
    assert np.max(np.abs(qd[after])) < 1e-12
    assert np.max(np.abs(tau(q[after]) - s_stop)) < 1e-12
    assert np.all(batch["modes"][0][after, 0] == 0)
    # λ_t = M g sin θ (the stick row holds the block up the slope), λ_N = M g cos θ, |λ_t| ≤ μ λ_N.
    lam_t, lam_n = batch["lam_t"][0][after, 0], batch["lam"][0][after, 0]
    np.testing.assert_allclose(lam_t, M * G * math.sin(THETA), rtol=1e-12)
    np.testing.assert_allclose(lam_n, M * G * math.cos(THETA), rtol=1e-12)
    assert np.all(np.abs(lam_t) <= 0.8 * lam_n)
    # Before the stop it slid up: λ_t = −μ λ_N, opposing v_t > 0.
    before = np.asarray(TS) < t_stop
    np.testing.assert_allclose(batch["lam_t"][0][before, 0], -0.8 * M * G * math.cos(THETA), rtol=1e-12)


def test_block_slides_back_when_friction_is_too_weak(batch):
    mu = 0.3
    _, t_stop, s_stop = up_the_ramp(V0, mu)
    kinds, times = batch["kinds"][1], batch["times"][1]
    assert list(kinds[:2]) == [5, 0]  # at v_t = 0 sticking would need |λ_t| > μ λ_N: "slip" back
    assert abs(times[0] - t_stop) < 1e-12  # as above: measured 2e-16
    ts = np.asarray(TS)
    after = ts > t_stop
    down = G * (math.sin(THETA) - mu * math.cos(THETA))
    expected = s_stop - 0.5 * down * (ts[after] - t_stop) ** 2
    # Quadratic motion: Tsit5 (order 5) integrates it exactly; measured 9e-15.
    np.testing.assert_allclose(tau(batch["q"][1][after]), expected, atol=1e-12)
    np.testing.assert_allclose(tau(batch["qd"][1][after]), -down * (ts[after] - t_stop), atol=1e-12)
    assert np.all(batch["modes"][1][after, 0] == -1)
    np.testing.assert_allclose(batch["lam_t"][1][after, 0], mu * M * G * math.cos(THETA), rtol=1e-12)


def test_floor_push_sticks_then_slips_at_the_closed_form_time(batch):
    mu = 0.5
    t_slip = mu * M * G / PUSH
    kinds, times = batch["kinds"][2], batch["times"][2]
    assert list(kinds[:2]) == [5, 0]  # "slip" when c t reaches μ M g, then the end
    # Root of μ λ_N − |λ_t| = μ M g − c t, linear: measured error 0.
    assert abs(times[0] - t_slip) < 1e-12
    ts = np.asarray(TS)
    x = batch["q"][2][:, 0]
    stuck, slipping = ts < t_slip, ts > t_slip
    assert np.max(np.abs(x[stuck])) < 1e-12
    np.testing.assert_allclose(batch["lam_t"][2][stuck, 0], -PUSH * ts[stuck], rtol=1e-12)
    d = ts[slipping] - t_slip
    # M ẍ = c t − μ M g from rest at t_s: a cubic, integrated exactly by Tsit5; measured 1.5e-14.
    expected = (
        PUSH * (ts[slipping] ** 3 - t_slip**3) / (6 * M)
        - PUSH * t_slip**2 * d / (2 * M)
        - 0.5 * mu * G * d**2
    )
    np.testing.assert_allclose(x[slipping], expected, atol=1e-12)
    assert np.all(batch["modes"][2][slipping, 0] == 1)


def test_gradients_of_the_stop_against_closed_form_and_differences(batch):
    a, t_stop, s_stop = up_the_ramp(V0, 0.8)
    jac = batch["jac"][0]  # d(t*, s*)/d(v0, μ, θ, c, A)
    dadmu = G * math.cos(THETA)
    # Closed forms: t* = v0/a, s* = v0²/(2a). Differentiated through the event root find;
    # measured relative errors ≤ 2e-14.
    np.testing.assert_allclose(jac[:, 0], [1 / a, V0 / a], rtol=1e-10)
    np.testing.assert_allclose(jac[:, 1], [-V0 * dadmu / a**2, -(V0**2) * dadmu / (2 * a**2)], rtol=1e-10)
    # Central differences with members at v0 ± h (t* is linear in v0: no truncation error; the
    # event times carry the root find's residual, / h: measured 3e-12 relative).
    plus, minus = batch["times"][4][0], batch["times"][5][0]
    np.testing.assert_allclose(jac[0, 0], (plus - minus) / (2 * STEP), rtol=1e-7)


def test_floor_pushed_to_and_fro_slips_sticks_and_slips_back(batch):
    mu = 0.3
    limit = mu * M * G  # the push A sin 2t breaks the block loose where |A sin 2t| = μ M g
    t1 = math.asin(limit / SHAKE) / 2
    t3 = math.pi / 2 + t1  # the push, now negative, breaks it loose the other way

    def speed(t):  # slipping forward from rest at t1: M v̇ = A sin 2t − μ M g
        return SHAKE / (2 * M) * (math.cos(2 * t1) - math.cos(2 * t)) - mu * G * (t - t1)

    lo, hi = 1.0, 1.8  # v > 0 at lo, < 0 at hi: the stop t2 by bisection to 1e-15
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if speed(mid) > 0 else (lo, mid)
    kinds, times = batch["kinds"][3], batch["times"][3]
    assert list(kinds) == [5, 4, 5, 0]  # slip, stick, slip (backwards), end
    # Event times: roots on the dense output (the motion is not polynomial here: the solver's
    # rtol 1e-10 bounds the state error, hence the time error through v̇ = O(1)); measured 3.4e-11.
    np.testing.assert_allclose(times[:3], [t1, lo, t3], atol=1e-9)
    modes = batch["modes"][3][:, 0]
    ts = np.asarray(TS)
    assert np.all(modes[(ts > t1) & (ts < lo)] == 1) and np.all(modes[(ts > lo) & (ts < t3)] == 0)
    assert np.all(modes[ts > t3] == -1) and np.all(modes[ts < t1] == 0)


def test_coulomb_options_and_errors():
    with pytest.raises(ValueError, match="mu must be a finite number"):
        jl.Coulomb(0, along, -0.1)
    with pytest.raises(ValueError, match="mu must be a scalar"):
        jl.Coulomb(0, along, [0.1, 0.2])
    with pytest.raises(TypeError, match="non-negative int"):
        jl.Coulomb(-1, along, 0.1)
    with pytest.raises(ValueError, match="holonomic"):
        jl.System(lagrangian, friction=jl.Coulomb(0, along, 0.1))
    with pytest.raises(ValueError, match="at most one"):
        jl.System(lagrangian, surface, friction=[jl.Coulomb(0, along, 0.1), jl.Coulomb(0, along, 0.2)])
    system = jl.System(lagrangian, surface, unilateral=0, friction=jl.Coulomb(3, along, 0.1))
    with pytest.raises(ValueError, match="contact rows"):
        jl.simulate(system, jnp.zeros(2), jnp.zeros(2), TS, args={"theta": 0.0, "c": 0.0, "A": 0.0})


def test_friction_needs_a_unilateral_contact_row_and_no_least_squares():
    # On a bilateral row λ_N may change sign, and μλ_N would be no bound (a "friction" pushing
    # along the motion): refused where the system is built.
    bilateral = jl.System(lagrangian, surface, friction=jl.Coulomb(0, along, 0.1))
    with pytest.raises(ValueError, match=r"contact rows \[0\], which are not unilateral"):
        jl.simulate(bilateral, jnp.zeros(2), jnp.zeros(2), TS, args={"theta": 0.0, "c": 0.0, "A": 0.0})
    with pytest.raises(ValueError, match="least_squares=True is not supported"):
        jl.System(lagrangian, surface, unilateral=0, least_squares=True, friction=jl.Coulomb(0, along, 0.1))


# ----------------------------------------------------------------------- the coefficient's range
SLOPE = {"theta": jnp.asarray(THETA), "c": jnp.asarray(0.0), "A": jnp.asarray(0.0)}


def released_on_the_ramp(mu, throw=True):
    """A block released at rest on the 30° ramp (μ an array leaf: one program per mode)."""
    system = jl.System(lagrangian, surface, forces=push, unilateral=0, friction=jl.Coulomb(0, along, mu))
    return jl.simulate(
        system, jnp.zeros(2), jnp.zeros(2), TS[:5], args=SLOPE, events=jl.Events(max_segments=4), throw=throw
    )


def slid(mu):
    return along(released_on_the_ramp(mu).q[-1], SLOPE)


def test_friction_coefficient_out_of_range_is_refused_in_every_mode():
    # Before: a traced μ < 0 ran, friction pushing the block up the slope (τ grew), and μ = NaN
    # read "the equations of motion became non-finite". The segment loop now checks μ before
    # the first step: FailureCode.FRICTION_COEFFICIENT, raised with the value eagerly (here
    # under grad, where μ is traced) and with the static message under jit and vmap.
    t = float(TS[4])
    down = G * (math.sin(THETA) - 0.3 * math.cos(THETA))
    np.testing.assert_allclose(slid(0.3), -0.5 * down * t**2, atol=1e-12)  # slides down: valid
    np.testing.assert_allclose(jax.grad(slid)(0.3), 0.5 * G * math.cos(THETA) * t**2, rtol=1e-10)
    with pytest.raises(jl.SimulationError, match=r"Coulomb contact 0 \(on holonomic row 0\) is mu = -0\.1"):
        jax.grad(slid)(-0.1)
    compiled = r"friction coefficient .*negative or not finite"
    with pytest.raises(Exception, match=compiled):
        jax.block_until_ready(jax.jit(slid)(-0.5))
    with pytest.raises(Exception, match=compiled):
        jax.block_until_ready(jax.vmap(slid)(jnp.array([0.3, jnp.nan])))
    kept = jax.jit(lambda mu: released_on_the_ramp(mu, throw=False))
    for mu in (-0.5, np.nan):
        traj = kept(jnp.asarray(mu))
        assert int(traj.failure.code) == jl.FailureCode.FRICTION_COEFFICIENT
        assert int(traj.failure.index) == 0
        np.testing.assert_array_equal(traj.failure.value, mu)
        assert np.all(np.isinf(traj.q[1:]))  # it did not run
    with pytest.raises(jl.SimulationError, match=r"mu = nan .*must be finite and >= 0"):
        traj.raise_if_failed()
