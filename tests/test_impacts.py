"""Impacts with restitution, Zeno accumulation, impulses in the log, event resets.

Compile-time budget: two compiled programs for the physics. The bouncing ball (under jit, vmap
and reverse-mode grad, with a second ball bounced by an event reset) serves the closed forms, the
batch, the finite differences (members of the same batch) and the reset; the three balls in a
row serve momentum and energy (eager, the restitution an array leaf: one program for every e).
Then one ball on a floor, its restitution an array leaf, in each mode (eager, jit, vmap, grad:
one program per mode and set of events, shared by the tests that use it) for the checks of the
restitution, the throw from the floor, the impact kind, the Zeno rule and the long elastic runs.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl

G = 9.81
SPAN = 5.0
ZENO = 1e-3 * SPAN  # zeno_time given: a rebound flying less than 5 ms is plastic (24 bounces)
SEGMENTS = 64


def two_balls(q, qd):
    """Ball 1 (z1) on a floor z1 ≥ 0 with restitution; ball 2 (z2) has no floor: an event with
    a reset ż2 → −e ż2 bounces it. Unit masses."""
    return 0.5 * (qd[0] ** 2 + qd[1] ** 2) - G * (q[0] + q[1])


def floor(q):
    return q[:1]  # f = z1 ≥ 0, λ ≥ 0 the floor's push


def reverse(q, qd, args):
    # Newton's law by hand, with the same Zeno rule as the floor (Events.zeno_time): a rebound
    # that would fly for less than ZENO (2 e |ż| / g) is not made; the ball then falls through.
    v = qd[1]
    bounce = 2.0 * args["e"] * jnp.abs(v) >= G * ZENO
    return q, qd.at[1].set(jnp.where(bounce, -args["e"] * v, v))


BOUNCE = jl.Event(lambda q, qd: q[1], terminal=False, direction=False, reset=reverse)
EVENTS = jl.Events(BOUNCE, max_segments=SEGMENTS, zeno_time=ZENO)


def bounce_times(e, h, count):
    """t_1 = √(2h/g), t_{n+1} = t_n + 2 eⁿ √(2h/g)."""
    t0 = math.sqrt(2 * h / G)
    return np.cumsum([t0] + [2 * e**n * t0 for n in range(1, count)])


def bounces_to_rest(e, h):
    """The first impact whose rebound would fly less than ZENO, 2 eⁿ √(2h/g) < ZENO."""
    return math.ceil(math.log(ZENO / (2 * math.sqrt(2 * h / G))) / math.log(e))


def apex_times(e, h, count):
    """The n-th apex, eⁿ √(2h/g) after the n-th bounce, at height e²ⁿ h."""
    t0 = math.sqrt(2 * h / G)
    return bounce_times(e, h, count) + np.array([e**n * t0 for n in range(1, count + 1)])


def second_bounces(params, ts):
    """(time of ball 1's 2nd contact, of ball 2's 2nd reset), and the run."""
    e, h = params
    system = jl.System(two_balls, floor, unilateral=jl.Unilateral(0, restitution=e))
    traj = jl.simulate(system, jnp.stack([h, h]), jnp.zeros(2), ts, args={"e": e}, events=EVENTS)
    log = traj.events
    # The floor's impacts: entries with an impulse on its row. The balls land together: the
    # contact and the reset are two entries at the same instant, or one when the reset's
    # segment end takes the touching, approaching ball 1 with it (an impact at a reset).
    contact = jnp.sort(jnp.where(log.impulses[:, 0] > 0, log.time, jnp.inf))[1]
    reset = jnp.sort(jnp.where(log.kind == 3, log.time, jnp.inf))[1]
    return jnp.stack([contact, reset]), (log, traj.q, traj.multipliers, traj.active)


# One program: jit(vmap(jacrev)), values and gradients of every member at once.
BATCH = jax.jit(jax.vmap(jax.jacrev(second_bounces, has_aux=True)))

E0, H0, STEP = 0.8, 1.0, 1e-5
MEMBERS = np.array(
    [
        [E0, H0],
        [0.5, 1.0],
        [0.6, 0.6],
        [E0 + STEP, H0],  # central differences: members of the same batch
        [E0 - STEP, H0],
        [E0, H0 + STEP],
        [E0, H0 - STEP],
    ]
)
APEXES = 6


def save_times(e, h):
    return np.concatenate([[0.0], apex_times(e, h, APEXES), [SPAN]])


@pytest.fixture(scope="module")
def batch():
    ts = np.stack([save_times(e, h) for e, h in MEMBERS])
    jac, (log, q, lam, active) = BATCH(jnp.asarray(MEMBERS), jnp.asarray(ts))
    return {
        "jac": np.asarray(jac),
        "log": jax.tree.map(np.asarray, log),
        "q": np.asarray(q),
        "lam": np.asarray(lam),
        "active": np.asarray(active),
        "ts": ts,
    }


def test_bounce_times_apex_heights_and_impulses(batch):
    for member in range(3):
        e, h = MEMBERS[member]
        log = jax.tree.map(lambda x: x[member], batch["log"])
        contacts = log.time[log.impulses[:, 0] > 0]
        n = min(8, bounces_to_rest(e, h) - 1)  # the rebounds before the plastic end
        # Exact: free flight is a parabola (Tsit5 integrates it without truncation error), the
        # event root find runs at 1e-13; measured max error 1.3e-13 s over the first 8.
        np.testing.assert_allclose(contacts[:n], bounce_times(e, h, n), rtol=0, atol=1e-12)
        # The reset ball (an Event with reset, no constraint) bounces at the same instants.
        resets = log.time[log.kind == 3]
        np.testing.assert_allclose(resets[:n], contacts[:n], rtol=0, atol=1e-12)
        # Apex heights e²ⁿ h, saved at the closed-form apex times, for both balls.
        apex = batch["q"][member, 1 : APEXES + 1]
        heights = e ** (2 * np.arange(1, APEXES + 1)) * h
        np.testing.assert_allclose(apex[:, 0], heights, rtol=0, atol=1e-12)
        np.testing.assert_allclose(apex[:, 1], heights, rtol=0, atol=1e-12)
        # Impulses Λ_n = (1 + e) m v_n, v_n = e^(n−1) √(2gh): in the log, on the floor's row.
        impulses = log.impulses[log.impulses[:, 0] > 0, 0]
        expected = (1 + e) * e ** np.arange(n) * math.sqrt(2 * G * h)
        np.testing.assert_allclose(impulses[:n], expected, rtol=1e-12)
        assert np.all(log.impulses[log.kind == 0] == 0)  # none at the end


def test_zeno_ends_in_persistent_contact(batch):
    for member in range(3):
        e, h = MEMBERS[member]
        log = jax.tree.map(lambda x: x[member], batch["log"])
        contacts = log.impulses[:, 0] > 0
        # The contact persists at the first impact whose rebound would fly less than ZENO:
        # 2 eⁿ √(2h/g) < ZENO (24 bounces for e = 0.8, h = 1 in 5 s).
        n_rest = bounces_to_rest(e, h)
        assert int(contacts.sum()) == n_rest
        # That impact is plastic: Λ = m v_n, v_n = e^(n−1) √(2gh).
        v_last = e ** (n_rest - 1) * math.sqrt(2 * G * h)
        np.testing.assert_allclose(log.impulses[contacts, 0][-1], v_last, rtol=1e-9)
        np.testing.assert_array_equal(log.active[contacts, 0], [False] * (n_rest - 1) + [True])
        t_rest = log.time[contacts][-1]
        np.testing.assert_allclose(t_rest, bounce_times(e, h, n_rest)[-1], atol=1e-11)
        # At rest on the floor: z1 = 0 exactly (projected), the floor carries the weight λ = m g.
        at_rest = batch["ts"][member] > t_rest
        assert at_rest[-1] and log.kind[int(log.count)] == 0  # the run reached its end
        np.testing.assert_allclose(batch["q"][member, at_rest, 0], 0.0, atol=1e-15)
        np.testing.assert_allclose(batch["lam"][member, at_rest, 0], G, rtol=1e-12)
        assert np.all(batch["active"][member, at_rest, 0])
        # The reset ball, by the same rule, stops reversing at the same impact and falls through.
        resets = log.time[log.kind == 3]
        np.testing.assert_allclose(resets, log.time[contacts], atol=1e-12)
        assert batch["q"][member, -1, 1] < 0


def test_gradients_of_bounce_times_against_closed_form_and_differences(batch):
    jac = batch["jac"]  # (member, [contact, reset], [e, h])
    t0 = math.sqrt(2 * H0 / G)
    # t_2 = √(2h/g)(1 + 2e): ∂t_2/∂e = 2√(2h/g), ∂t_2/∂h = (1 + 2e) √(2h/g) / (2h).
    exact = np.array([2 * t0, (1 + 2 * E0) * t0 / (2 * H0)])
    np.testing.assert_allclose(jac[0, 0], exact, rtol=1e-10)  # measured 1.1e-14
    np.testing.assert_allclose(jac[0, 1], exact, rtol=1e-10)  # through the reset: 1.1e-14
    # Central differences from members 3–6 of the same batch (step 1e-5: no truncation error
    # in e, t_2 is linear in it, O(step²) ~ 1e-11 in h; the event times' own error, far below
    # the root finder's 1e-13 (Newton converges quadratically), over 2e-5): measured 4.5e-11.
    log = batch["log"]
    values = np.stack([log.time[m][log.impulses[m, :, 0] > 0][1] for m in range(3, 7)])
    fd = np.array([values[0] - values[1], values[2] - values[3]]) / (2 * STEP)
    np.testing.assert_allclose(jac[0, 0], fd, rtol=1e-8)


def test_batch_matches_members(batch):
    # The batched program (jit(vmap(jacrev))) against members run on their own, eagerly. The
    # impacts and resets at coinciding instants may be split into log entries differently
    # (round-off decides which of two roots 1e-16 apart comes first), so the impact and reset
    # times, the saved states and the second bounce times are compared, not the raw entries.
    log = batch["log"]
    for member in (0, 2):
        alone, (log1, q1, _, _) = second_bounces(
            jnp.asarray(MEMBERS[member]), jnp.asarray(batch["ts"][member])
        )
        np.testing.assert_allclose(
            [log.time[member][log.impulses[member, :, 0] > 0][1], log.time[member][log.kind[member] == 3][1]],
            alone,
            rtol=0,
            atol=1e-13,
        )
        for mask, mask1 in (
            (log.impulses[member, :, 0] > 0, log1.impulses[:, 0] > 0),
            (log.kind[member] == 3, log1.kind == 3),
        ):
            np.testing.assert_allclose(log.time[member][mask], log1.time[mask1], rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch["q"][member], q1, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------- three balls in a row
def row_lagrangian(q, qd):
    return 0.5 * jnp.sum(qd**2)  # unit masses on a line, no gravity


def gaps(q):
    return jnp.stack([q[1] - q[0] - 1.0, q[2] - q[1] - 1.0])  # unit diameters: gaps ≥ 0


ROW_TS = jnp.linspace(0.0, 8.0, 9)
# A condition on ball 1's velocity: for e = 1 the impact stops ball 1 and the condition sits at
# 0 from then on (ċ = c̈ = 0). Before, it kept the side it had and fired at every segment
# ("needed more than max_segments"); now it is on no side and never fires. (Module level: one
# compiled program for both e.)
ROW_EVENTS = jl.Events(jl.Event(lambda q, qd: qd[0], terminal=False, direction=False), max_segments=8)


def three_balls(e):
    system = jl.System(row_lagrangian, gaps, unilateral=jl.Unilateral((0, 1), restitution=e))
    q0, qd0 = jnp.array([0.0, 2.0, 4.0]), jnp.array([1.0, 0.0, 0.0])
    return jl.simulate(system, q0, qd0, ROW_TS, events=ROW_EVENTS)


@pytest.mark.parametrize("e", [1.0, 0.5])
def test_three_balls_momentum_and_energy_at_each_impact(e):
    log = three_balls(jnp.asarray(e)).events  # an array: one compiled program for both
    real = np.asarray(log.kind)[: int(log.count)]
    assert np.all(real == jl.EventKind.IMPACT) and len(real) >= 2  # rebounds (e > 0): impacts
    before = np.array([1.0, 0.0, 0.0])
    for k in range(len(real)):
        after = np.asarray(log.qd[k])
        # Momentum: exact at each impact up to round-off (measured 0; energy 2e-16).
        np.testing.assert_allclose(after.sum(), 1.0, atol=1e-14)
        # Newton's law on the row that hit: relative velocity reversed and scaled by e.
        i = int(log.index[k])
        np.testing.assert_allclose(after[i + 1] - after[i], -e * (before[i + 1] - before[i]), atol=1e-14)
        # Energy lost: ½ μ (1 − e²) v_rel², μ = m/2 (zero for e = 1).
        lost = 0.5 * before @ before - 0.5 * after @ after
        np.testing.assert_allclose(lost, 0.25 * (1 - e**2) * (before[i + 1] - before[i]) ** 2, atol=1e-14)
        # Impulse = the momentum handed over: Λ = m Δv of the ball ahead.
        np.testing.assert_allclose(log.impulses[k, i], after[i + 1] - before[i + 1], atol=1e-14)
        before = after
    if e == 1.0:  # the momentum passes down the row: (1, 0, 0) → (0, 1, 0) → (0, 0, 1)
        assert len(real) == 2
        np.testing.assert_allclose(log.qd[1], [0.0, 0.0, 1.0], atol=1e-15)
        np.testing.assert_allclose(log.time[:2], [1.0, 2.0], atol=1e-12)


# ----------------------------------------------------------------------- options and errors
def test_unilateral_options_and_errors():
    law = jl.Unilateral((2, 0), restitution=[0.3, 0.7])
    assert law.indices == (0, 2)
    np.testing.assert_allclose(law.restitution, [0.7, 0.3])  # sorted with the indices
    system = jl.System(two_balls, floor, unilateral=jl.Unilateral(0, 0.5))
    assert system.unilateral == (0,) and system.unilateral_law is not None
    assert jl.System(two_balls, floor, unilateral=0).unilateral_law is None  # plastic
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        jl.Unilateral(0, restitution=1.5)
    with pytest.raises(ValueError, match="one entry per index"):
        jl.Unilateral((0, 1), restitution=[0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="terminal=False"):
        jl.Event(lambda q, qd: q[0], reset=reverse)
    with pytest.raises(ValueError, match="zeno_time"):
        jl.Events(zeno_time=-1.0)
    bad = jl.Event(lambda q, qd: q[1], terminal=False, reset=lambda q, qd: (q, qd[:1]))
    with pytest.raises(ValueError, match=r"reset of event 0 .* shape \(2,\)"):
        jl.simulate(jl.System(two_balls), jnp.ones(2), jnp.zeros(2), jnp.linspace(0, 1, 3), events=bad)


# ----------------------------------------------------------------------- a reset off the manifold
def test_reset_off_the_constraint_manifold_is_projected():
    # A particle on the unit circle (Cartesian, bilateral x² + y² − 1 = 0), no gravity, turning
    # at unit speed. At t = 0.3 a reset moves it off the circle (q → 1.1 q) and adds a radial
    # velocity: the run continues from the mass-weighted projection, back on the circle with
    # q·q̇ = 0 (the radial part removed, the tangential speed kept).
    system = jl.System(lambda q, qd: 0.5 * jnp.sum(qd**2), lambda q: jnp.array([q @ q - 1.0]))
    kick = jl.Event(lambda q, qd, t: t - 0.3, terminal=False, reset=lambda q, qd: (1.1 * q, qd + 2.0 * q))
    q0, qd0 = jnp.array([1.0, 0.0]), jnp.array([0.0, 1.0])
    traj = jl.simulate(system, q0, qd0, jnp.linspace(0.0, 1.0, 5), events=jl.Events(kick, max_segments=3))
    log = traj.events
    assert log.kinds() == ["user", "end"]
    q, qd = np.asarray(log.q[0]), np.asarray(log.qd[0])
    # Newton's projection converges quadratically from 10% off: round-off after two steps.
    np.testing.assert_allclose(q @ q, 1.0, atol=1e-12)
    np.testing.assert_allclose(q @ qd, 0.0, atol=1e-12)
    np.testing.assert_allclose(q, [math.cos(0.3), math.sin(0.3)], atol=1e-9)  # radial move undone
    np.testing.assert_allclose(np.hypot(*qd), 1.0, atol=1e-9)  # tangential speed kept
    np.testing.assert_allclose(traj.q[-1], [math.cos(1.0), math.sin(1.0)], atol=1e-8)


def test_unilateral_true_is_not_an_index():
    with pytest.raises(TypeError, match="give the indices of the one-sided holonomic rows"):
        jl.System(lambda q, qd: 0.5 * qd[0] ** 2, lambda q: q, unilateral=True)


# ----------------------------------------------------------------------- one ball, every mode
# A unit mass on a floor z ≥ 0, restitution e an array leaf: every call below with the same
# shapes and events shares its compiled program, whatever e, q0 and qd0 are.
def ball_lagrangian(q, qd):
    return 0.5 * qd[0] ** 2 - G * q[0]


def ball(e):
    return jl.System(ball_lagrangian, floor, unilateral=jl.Unilateral(0, restitution=e))


BALL_TS = jnp.linspace(0.0, 3.0, 7)
BALL_EVENTS = jl.Events(max_segments=32)


def ball_run(e, q0, qd0, throw=True):
    return jl.simulate(ball(e), q0, qd0, BALL_TS, events=BALL_EVENTS, throw=throw)


def first_impacts(e, q0, qd0):
    """The first four impact times (inf where there are fewer)."""
    return ball_run(e, q0, qd0).events.impact_times(4)


def second_bounce(e):
    """The second impact of the ball dropped from 1 m: t₂ = √(2h/g)(1 + 2e)."""
    return ball_run(e, jnp.ones(1), jnp.zeros(1)).events.impact_times(2)[1]


ONE, ZERO = jnp.ones(1), jnp.zeros(1)


def test_restitution_outside_zero_one_is_refused_in_every_mode():
    # Before: a traced e ran as given: e = 1.5 sent a ball dropped from 1 m up to 5 m, e = −0.5
    # stuck it to the floor, NaN ended in "max_steps ... stiffness", and jax.grad of the second
    # bounce at e = 1.2 returned 0.903 (eagerly too: under grad e is traced). Now the segment
    # loop checks e before the first step: FailureCode.RESTITUTION, raised with the value
    # eagerly and with the static message (naming restitution and [0, 1]) under jit and vmap.
    with pytest.raises(ValueError, match=r"restitution must lie in \[0, 1\]"):
        ball(1.5)  # concrete: refused when it is built, as before
    with pytest.raises(jl.SimulationError, match=r"restitution = 1\.2 .*finite number in \[0, 1\]"):
        jax.grad(second_bounce)(1.2)
    compiled = r"coefficient of restitution .*outside \[0, 1\] or not finite"
    run = jax.jit(first_impacts)
    for e in (1.5, -0.5, np.nan):
        with pytest.raises(Exception, match=compiled):
            jax.block_until_ready(run(jnp.asarray(e), ONE, ZERO))
    with pytest.raises(Exception, match=compiled):
        jax.block_until_ready(
            jax.vmap(first_impacts)(jnp.array([0.5, 1.5]), jnp.ones((2, 1)), jnp.zeros((2, 1)))
        )
    # throw=False: the record says what and which, and raises the full message later.
    kept = jax.jit(lambda e: ball_run(e, ONE, ZERO, throw=False))(jnp.asarray(1.5))
    assert int(kept.failure.code) == jl.FailureCode.RESTITUTION
    assert int(kept.failure.index) == 0 and float(kept.failure.value) == 1.5
    assert float(kept.failure.t) == 0.0 and np.all(np.isinf(kept.q[1:]))  # it did not run
    with pytest.raises(jl.SimulationError, match=r"unilateral row 0 is restitution = 1\.5"):
        kept.raise_if_failed()


def test_ball_thrown_up_from_the_floor_flies():
    # Before: f(q0) = 0 with ḟ = w > 0 (leaving the floor) was refused as "off the constraint
    # manifold", and the advice (consistent_initial_state) would have zeroed the throw. A
    # one-sided constraint that separates at t0 is inactive: the ball flies, lands after 2w/g
    # and, rebounding at e·w, again after 2ew/g more: 2w/g and 2w/g (1 + e).
    w, e = 3.0, 0.5
    expected = 2 * w / G * np.array([1.0, 1.0 + e])
    q0, qd0 = jnp.zeros(1), jnp.array([w])
    eager = np.asarray(first_impacts(jnp.asarray(e), q0, qd0))
    # A free flight is a parabola (integrated exactly), the landings found to 1e-13.
    np.testing.assert_allclose(eager[:2], expected, rtol=0, atol=1e-12)
    jitted = np.asarray(jax.jit(first_impacts)(jnp.asarray(e), q0, qd0))
    mapped = np.asarray(jax.vmap(first_impacts)(jnp.array([e, 0.8]), jnp.zeros((2, 1)), jnp.full((2, 1), w)))
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=1e-12)
    np.testing.assert_allclose(mapped[0], eager, rtol=0, atol=1e-12)
    np.testing.assert_allclose(mapped[1, :2], 2 * w / G * np.array([1.0, 1.8]), rtol=0, atol=1e-12)
    # Thrown up at t0 it is not in contact: the first entry of the log is the landing.
    log = ball_run(jnp.asarray(e), q0, qd0).events
    assert log.kinds()[:2] == ["impact", "impact"]
    assert not bool(log.active[0, 0])


def test_impacts_have_their_own_kind_and_times_under_grad():
    # Before: every impact was a "contact" in traj.events.kinds(). A rebound is an IMPACT, the
    # plastic impact that ends the bouncing (the ball at rest) a CONTACT.
    e = 0.5  # at rest (a rise below the constraint tolerance) within 3 s: 14 impacts
    log = ball_run(jnp.asarray(e), ONE, ZERO).events
    kinds = log.kinds()
    rest = math.ceil(math.log(1e-8) / (2 * math.log(e)))
    assert kinds == ["impact"] * (rest - 1) + ["contact", "end"], kinds
    assert bool(jnp.all(log.kind[: rest - 1] == jl.EventKind.IMPACT))
    times = np.asarray(log.impact_times())
    np.testing.assert_allclose(times[:rest], bounce_times(e, 1.0, rest), rtol=0, atol=1e-11)
    assert np.all(np.isinf(times[rest:])) and times.shape == (32,)
    assert np.isinf(np.asarray(log.impact_times(40))[-1]) and log.impact_times(40).shape == (40,)
    np.testing.assert_array_equal(log.impact_times(3, index=0), times[:3])
    # d t₂ / d e = 2 √(2h/g) (t₂ = √(2h/g)(1 + 2e) = t₁ + 2e v₁/g): eagerly, and under
    # jit(vmap(grad)) in one program, against the closed form and central differences.
    t1 = math.sqrt(2.0 / G)
    np.testing.assert_allclose(second_bounce(0.8), t1 * 2.6, rtol=0, atol=1e-12)
    np.testing.assert_allclose(jax.grad(second_bounce)(0.8), 2 * t1, rtol=1e-10)
    step = 1e-5
    members = jnp.array([0.8, 0.8 + step, 0.8 - step])
    values, grads = jax.jit(jax.vmap(jax.value_and_grad(second_bounce)))(members)
    np.testing.assert_allclose(grads, 2 * t1, rtol=1e-10)
    # t₂ is linear in e: the differences have no truncation error, only the event times' own
    # (~1e-13 over 2e-5).
    np.testing.assert_allclose((values[1] - values[2]) / (2 * step), 2 * t1, rtol=1e-7)
    # The same program refuses a batch with an e out of range (restitution checked under vmap).
    with pytest.raises(Exception, match=r"coefficient of restitution"):
        jax.block_until_ready(
            jax.jit(jax.vmap(jax.value_and_grad(second_bounce)))(jnp.array([0.8, 1.2, 0.5]))
        )


# ----------------------------------------------------------------------- Zeno by the physics
ZENO_TS = jnp.linspace(0.0, 3.0, 32)


def test_default_zeno_rule_does_not_depend_on_the_save_horizon():
    # Before: the default zeno_time was 10⁻³ of the saved span, so the same ball (e = 0.9, from
    # 1 m) saved to 1000 s had a first impact "shorter than 1 s" and stuck to the floor at once
    # (4 bounces in [0, 3] when saved to 3 s, none when saved to 1000 s). The default now ends
    # the bouncing by the impact alone: plastic once the rebound would rise less than the
    # constraint tolerance (1e-8), the (88)th impact: e^(2k) h ≤ 1e-8.
    e = 0.9
    events = jl.Events(max_segments=128)
    short = jl.simulate(ball(jnp.asarray(e)), ONE, ZERO, ZENO_TS, events=events)
    long_ts = jnp.concatenate([ZENO_TS[:-1], jnp.array([1000.0])])  # the same shape: one program
    long = jl.simulate(ball(jnp.asarray(e)), ONE, ZERO, long_ts, events=events)
    closed = bounce_times(e, 1.0, 4)  # 0.4515, 1.2643, 1.9957, 2.6541: four bounces in [0, 3]
    for traj in (short, long):
        times = np.asarray(traj.events.impact_times(5))
        np.testing.assert_allclose(times[:4], closed, rtol=0, atol=1e-12)
    assert (
        np.isinf(np.asarray(short.events.impact_times(5))[4]) and float(long.events.impact_times(5)[4]) > 3.0
    )
    np.testing.assert_allclose(long.q[:-1], short.q[:-1], rtol=0, atol=1e-12)
    # The long run comes to rest at the closed-form impact and time, and lies there (λ = m g).
    rest = math.ceil(math.log(1e-8) / (2 * math.log(e)))
    assert rest == 88
    kinds = long.events.kinds()
    assert kinds == ["impact"] * (rest - 1) + ["contact", "end"]
    t_rest = float(long.events.impact_times()[rest - 1])
    # bounce_times sums 88 flights (the sum's round-off ~1e-13) against the event times: 1e-11.
    np.testing.assert_allclose(t_rest, bounce_times(e, 1.0, rest)[-1], rtol=0, atol=1e-11)
    assert t_rest < math.sqrt(2.0 / G) * (1 + 2 * e / (1 - e))  # before the accumulation point
    np.testing.assert_allclose(long.q[-1], 0.0, atol=1e-15)
    np.testing.assert_allclose(long.multipliers[-1], G, rtol=1e-12)


def test_zeno_advice_counts_the_geometric_series_and_names_zeno_time():
    # Before: a long Zeno sequence (e = 0.999, zeno_time = 1e-9) out of segments was extrapolated
    # linearly from the time reached: "about 2305 segments are needed, max_segments=4096",
    # where the bouncing needs ~20,600. Now the record counts the impacts by the geometric
    # series of the flights (2 eᵏ √(2h/g) < zeno_time from impact k on) and the message names
    # zeno_time as the other lever.
    e, zeno = 0.999, 1e-9
    events = jl.Events(max_segments=64, zeno_time=zeno)
    plastic_at = math.ceil(math.log(zeno / (2 * math.sqrt(2.0 / G))) / math.log(e))  # 20,611
    with pytest.raises(jl.SimulationError) as info:
        jl.simulate(ball(jnp.asarray(e)), ONE, ZERO, jnp.array([0.0, 2000.0]), events=events)
    text = str(info.value)
    needed = int(text.split("run needs about ")[1].split(" segments")[0].replace(",", ""))
    assert needed == plastic_at + 1  # the impacts and the end
    assert "max_segments=32768" in text and "zeno_time" in text and "e = 0.999" in text
    kept = jl.simulate(ball(jnp.asarray(e)), ONE, ZERO, jnp.array([0.0, 2000.0]), events=events, throw=False)
    assert int(kept.failure.code) == jl.FailureCode.MAX_SEGMENTS and int(kept.failure.index) == 0
    assert float(kept.failure.value) == plastic_at + 1


# ----------------------------------------------------------------------- long elastic runs
# 400 s of an elastic ball (e = 1, an array): 443 impacts from 1 m, 44 from 100 m.
LONG_EVENTS = jl.Events(max_segments=448)
LONG_TS = jnp.array([0.0, 400.0])


def elastic_impacts(h):
    traj = jl.simulate(ball(jnp.asarray(1.0)), jnp.stack([h]), ZERO, LONG_TS, events=LONG_EVENTS)
    return traj.events.impact_times(), traj.events.count


def test_long_elastic_run_in_every_mode():
    # Before: from 1 m it ran eagerly and failed under jit ("the diffrax solver reported a
    # failure": the root finder's maximum steps), from 100 m it failed in both, at some landing
    # after t = 256 s. There the spacing of float64 times is 5.7e-14 s, and the contact
    # condition (the gap over the time since the rebound, whose rate at a landing is g/2)
    # cannot get below Newton's |c| < 1e-13 at every landing: Newton's step rounded to 0 and
    # repeated itself. It was chance which landings (and which compiled program) failed. The
    # default root finder now also stops at a step below the resolution of t.
    times, count = elastic_impacts(jnp.asarray(100.0))
    k = np.arange(int(count))
    t1 = math.sqrt(2 * 100.0 / G)
    np.testing.assert_allclose(np.asarray(times)[: int(count)], t1 * (2 * k + 1), rtol=0, atol=1e-9)
    batch_times, counts = jax.jit(jax.vmap(elastic_impacts))(jnp.array([1.0, 100.0]))
    assert [int(c) for c in counts] == [443, 44]
    for member, h in enumerate((1.0, 100.0)):
        n = int(counts[member])
        t1 = math.sqrt(2 * h / G)
        # t_k = √(2h/g)(2k + 1); the error grows with the landings (measured 1.4e-10 at 400 s).
        np.testing.assert_allclose(batch_times[member, :n], t1 * (2 * np.arange(n) + 1), rtol=0, atol=1e-9)


def test_default_root_finder_stops_at_the_resolution_of_t():
    # c(t) = 4.9 (t − r) with r halfway between two float64 numbers near 300 s: |c| ≥ 1.4e-13
    # at every representable t, so |c| < atol = 1e-13 cannot hold.
    import optimistix as optx

    from jaxlag._events import ResolvedNewton, root_finder_for

    t0 = 300.0
    half = np.spacing(t0) / 2

    def condition(t, _):
        return 4.9 * (t - t0) - 4.9 * half

    options = {"lower": jnp.asarray(299.0), "upper": jnp.asarray(301.0)}
    plain = optx.root_find(
        condition, optx.Newton(rtol=1e-13, atol=1e-13), jnp.asarray(301.0), options=options, throw=False
    )
    assert plain.result != optx.RESULTS.successful  # the failure of the long runs
    finder = root_finder_for(jl.Events().root_finder, jnp.float64)
    assert isinstance(finder, ResolvedNewton) and finder.atol == finder.rtol == 1e-13
    found = optx.root_find(condition, finder, jnp.asarray(301.0), options=options, throw=False)
    assert found.result == optx.RESULTS.successful
    assert abs(float(found.value) - (t0 + half)) <= np.spacing(t0)


def test_system_methods_take_unilateral_rows_as_simulate_starts():
    """``System.accelerations``/``multipliers`` at a state: a unilateral row acts where it
    touches and does not separate, as at the start of a run. A particle above the floor falls
    freely (``λ = 0``); resting on it, ``λ = m g`` and ``q̈ = 0``; leaving it upwards, free
    fall again. (They used to take every row as acting: the particle above the floor was held.)"""
    m, g = 2.0, 9.81
    particle = jl.System(
        lambda q, qd: 0.5 * m * qd @ qd - m * g * q[1],
        holonomic=lambda q: jnp.array([q[1]]),
        unilateral=(0,),
    )
    above = particle.accelerations(jnp.array([0.0, 1.0]), jnp.array([0.3, 0.0]))
    np.testing.assert_allclose(above, [0.0, -g], rtol=0, atol=1e-12)
    np.testing.assert_allclose(particle.multipliers(jnp.array([0.0, 1.0]), jnp.zeros(2)), [0.0], atol=1e-12)
    resting = (jnp.array([0.0, 0.0]), jnp.array([0.3, 0.0]))
    np.testing.assert_allclose(particle.accelerations(*resting), [0.0, 0.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(particle.multipliers(*resting), [m * g], rtol=1e-12)
    np.testing.assert_allclose(particle.constraint_forces(*resting), [0.0, m * g], rtol=0, atol=1e-12)
    leaving = particle.accelerations(jnp.array([0.0, 0.0]), jnp.array([0.0, 1.0]))
    np.testing.assert_allclose(leaving, [0.0, -g], rtol=0, atol=1e-12)
