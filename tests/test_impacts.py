"""Impacts with restitution, Zeno accumulation, impulses in the log, event resets.

Compile-time budget: two compiled programs. The bouncing ball (under jit, vmap and reverse-mode
grad, with a second ball bounced by an event reset) serves the closed forms, the batch, the
finite differences (members of the same batch) and the reset; the three balls in a row serve
momentum and energy (eager, the restitution an array leaf: one program for every e).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl

G = 9.81
SPAN = 5.0
ZENO = 1e-3 * SPAN  # Events' default zeno_time: 10⁻³ of the simulated span
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
EVENTS = jl.Events(BOUNCE, max_segments=SEGMENTS)


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
    assert np.all(real == 2) and len(real) >= 2
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
