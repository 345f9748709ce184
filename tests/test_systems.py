r"""Every model in ``jaxlag.systems`` simulated briefly and checked against a closed form or an invariant.

Each expected value is derived in a comment from the model's documented Lagrangian and the
library's sign convention ``M q̈ = F + Jᵀλ + Aᵀμ`` (not taken from the code under test). Unless a
test says otherwise the integration uses the library default ``PIDController(rtol=1e-10,
atol=1e-10)``: over the short horizons here (≤ one period) the global error stays near 1e-10,
so trajectory comparisons are asserted at 1e-8 and conserved quantities at 1e-9 relative.
State-wise identities (a multiplier recomputed at a saved state) are asserted at 1e-9 because
they inherit the trajectory's error.

To keep compilation time down (one compiled simulation per model and form) the runs skip what is
tested elsewhere: initial states are built exactly on the constraint manifold, so the initial-state
validation is off, and the per-step projection is off (over ≤ 2 s at rtol 1e-10 the index-1
drift stays near 1e-10, below every tolerance here).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

import jaxlag as jl
import jaxlag.systems as systems

jax.config.update("jax_enable_x64", True)

G = 9.81


def simulate(system, q0, qd0, ts, args=None):
    return jl.simulate(
        system,
        jnp.asarray(q0, float),
        jnp.asarray(qd0, float),
        jnp.asarray(ts, float),
        args=args,
        checks=jl.Checks(initial_state=False),
        projection=None,
    )


def assert_conserved(values, rtol=1e-9):
    values = np.asarray(values)
    scale = max(np.max(np.abs(values)), 1.0)
    assert np.max(np.abs(values - values[0])) <= rtol * scale, values - values[0]


# --------------------------------------------------------------------------------------------
# Pendulums
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("form", ["generalized", "cartesian"])
def test_simple_pendulum_half_period(form):
    # Released from rest at θ₀: half a period later it is at −θ₀, with the exact period
    # T = 4 √(l/g) K(sin²(θ₀/2)) (complete elliptic integral, parameter m = k²).
    l, th0 = 1.3, 1.0
    args = {"m": 0.8, "l": l}
    half = 2 * math.sqrt(l / G) * scipy.special.ellipk(math.sin(th0 / 2) ** 2)
    if form == "generalized":
        q0, qd0 = [th0], [0.0]
    else:
        q0, qd0 = [l * math.sin(th0), -l * math.cos(th0)], [0.0, 0.0]
    traj = simulate(systems.simple_pendulum(form), q0, qd0, jnp.linspace(0, half, 5), args)
    theta = traj.q[:, 0] if form == "generalized" else jnp.arctan2(traj.q[:, 0], -traj.q[:, 1])
    np.testing.assert_allclose(theta[-1], -th0, atol=1e-8)
    assert_conserved(traj.energy)
    if form == "cartesian":
        # f = |x| − l: λ = −m l θ̇² − m g cos θ (minus the tension), with θ̇ from energy.
        thd2 = 2 * G / l * (np.cos(theta) - math.cos(th0))
        np.testing.assert_allclose(traj.multipliers[:, 0], -0.8 * (l * thd2 + G * np.cos(theta)), rtol=1e-9)


def _chain_state(angles, rates, lengths):
    """Cartesian (x_k, y_k) and velocities of a planar chain with absolute angles."""
    x = np.cumsum(lengths * np.sin(angles))
    y = -np.cumsum(lengths * np.cos(angles))
    vx = np.cumsum(lengths * np.cos(angles) * rates)
    vy = np.cumsum(lengths * np.sin(angles) * rates)
    return np.stack([x, y], -1).reshape(-1), np.stack([vx, vy], -1).reshape(-1)


@pytest.mark.parametrize("n", [2, 3])
def test_chains_generalized_and_cartesian_agree(n):
    # The same motion in absolute angles and in Cartesian coordinates with rod constraints:
    # positions agree at the end, and the energy (T + V, time-independent) is conserved in both.
    angles, rates = np.array([0.9, -0.4, 0.3])[:n], np.array([0.5, 1.0, -1.5])[:n]
    if n == 2:
        lengths = np.array([1.0, 0.7])
        args = {"m1": 1.0, "m2": 0.5, "l1": 1.0, "l2": 0.7}
        generalized, cartesian = systems.double_pendulum(), systems.double_pendulum("cartesian")
    else:
        lengths = np.array([0.6, 0.5, 0.8])
        args = {"m": np.array([1.0, 0.7, 0.4]), "l": lengths}
        generalized = systems.n_link_pendulum(3)
        cartesian = systems.n_link_pendulum(3, "cartesian")
    ts = jnp.linspace(0, 0.6, 4)
    a = simulate(generalized, angles, rates, ts, args)
    x0, v0 = _chain_state(angles, rates, lengths)
    b = simulate(cartesian, x0, v0, ts, args)
    xa, _ = _chain_state(np.asarray(a.q[-1]), np.asarray(a.qd[-1]), lengths)
    np.testing.assert_allclose(b.q[-1], xa, atol=1e-8)
    np.testing.assert_allclose(a.energy, b.energy, rtol=1e-9)
    assert_conserved(a.energy)
    assert_conserved(b.energy)


@pytest.mark.parametrize("form", ["generalized", "cartesian"])
def test_spherical_pendulum_conical_motion(form):
    # Conical pendulum: θ̈ = sinθ cosθ φ̇² − (g/l) sinθ = 0 for φ̇² = g/(l cos θ₀); the bob
    # circles at constant height: θ(t) = θ₀, φ(t) = φ̇ t.
    l, th0 = 0.9, 0.6
    rate = math.sqrt(G / (l * math.cos(th0)))
    ts = jnp.linspace(0, 1.0, 5)
    if form == "generalized":
        traj = simulate(systems.spherical_pendulum(), [th0, 0.0], [0.0, rate], ts, {"m": 1.0, "l": l})
        np.testing.assert_allclose(traj.q[:, 0], th0, atol=1e-9)
        np.testing.assert_allclose(traj.q[:, 1], rate * ts, rtol=1e-9)
        assert_conserved(traj.momenta[:, 1])  # p_φ = L_z: φ is cyclic
    else:
        rho = l * math.sin(th0)
        traj = simulate(
            systems.spherical_pendulum("cartesian"),
            [rho, 0.0, -l * math.cos(th0)],
            [0.0, rho * rate, 0.0],
            ts,
            {"m": 1.0, "l": l},
        )
        expected = np.stack(
            [rho * np.cos(rate * ts), rho * np.sin(rate * ts), np.full(ts.shape, -l * math.cos(th0))], -1
        )
        np.testing.assert_allclose(traj.q, expected, atol=1e-8)
    assert_conserved(traj.energy)


def test_free_chain_centre_of_mass():
    # No external force but gravity: the centre of mass moves as a projectile,
    # x_cm = x₀ + v_x t, y_cm = y₀ + v_y t − ½ g t² (the link forces are internal).
    chain = systems.free_chain(3)
    q0 = np.array([0.0, 0.0, 1.0, 0.0, 1.0, 1.0])
    qd0 = np.array([0.3, 0.1, 0.3, -0.5, 1.0, -0.5])  # keeps both link lengths
    ts = jnp.linspace(0, 1.0, 5)
    traj = simulate(chain, q0, qd0, ts, {"g": 2.0})
    cm = np.asarray(traj.q).reshape(-1, 3, 2).mean(axis=1)
    v = qd0.reshape(3, 2).mean(axis=0)
    expected = np.stack([1 / 3 * 2 + v[0] * ts, 1 / 3 + v[1] * ts - 0.5 * 2.0 * ts**2], -1)
    np.testing.assert_allclose(cm, expected, atol=1e-8)
    assert_conserved(traj.energy)


def test_cart_pole_with_a_constant_force():
    # With u = F on the cart: ṗ_x = F exactly (x is cyclic apart from the force), so
    # p_x(t) = p_x(0) + F t, and the energy gains the work: h(t) − h(0) = F (x(t) − x(0)).
    system, force = systems.cart_pole(), 0.7
    args = {"M": 1.0, "m": 0.3, "l": 0.8, "force": force}
    ts = jnp.linspace(0, 1.0, 5)
    traj = simulate(system, [0.0, 0.2], [0.1, 0.0], ts, args)
    p = traj.momenta
    np.testing.assert_allclose(p[:, 0], p[0, 0] + force * ts, atol=1e-9)
    np.testing.assert_allclose(traj.energy - traj.energy[0], force * (traj.q[:, 0] - traj.q[0, 0]), atol=1e-9)
    # A feedback controller instead of the constant force: u = −k ẋ, with k read from args.
    # The generalized forces differ from the uncontrolled ones by exactly (u, 0).
    damped = systems.cart_pole(lambda q, qd, args: -args["k"] * qd[0])
    q, qd = jnp.array([0.1, 0.2]), jnp.array([0.3, -0.4])
    forces = jax.jit(lambda s, a: s.generalized_forces(q, qd, 0.0, a), static_argnums=0)
    np.testing.assert_allclose(
        forces(damped, {"k": 2.0}) - forces(system, None), [-2.0 * 0.3, 0.0], atol=1e-14
    )


# --------------------------------------------------------------------------------------------
# Beads and particles on curves and surfaces
# --------------------------------------------------------------------------------------------


def test_bead_on_spinning_hoop_both_forms():
    # ω² < g/R: the bead oscillates about the bottom. Generalized form: the Jacobi integral
    # h = ½ m R² (θ̇² − ω² sin²θ) − m g R cos θ is conserved (L has no explicit t). The Cartesian
    # form (sphere + rotating plane, rheonomic) must give the same polar angle.
    R, w, th0 = 0.5, 3.0, 0.5
    args = {"R": R, "omega": w}
    ts = jnp.linspace(0, 1.0, 5)
    a = simulate(systems.bead_on_hoop(), [th0], [0.0], ts, args)
    th, thd = np.asarray(a.q[:, 0]), np.asarray(a.qd[:, 0])
    assert_conserved(0.5 * R**2 * (thd**2 - w**2 * np.sin(th) ** 2) - G * R * np.cos(th))
    np.testing.assert_allclose(a.energy, a.energy[0], atol=1e-9)
    x0 = [R * math.sin(th0), 0.0, -R * math.cos(th0)]
    v0 = [0.0, w * R * math.sin(th0), 0.0]  # co-rotating with the hoop
    b = simulate(systems.bead_on_hoop("cartesian"), x0, v0, ts, args)
    rho = np.hypot(np.asarray(b.q[:, 0]), np.asarray(b.q[:, 1]))
    np.testing.assert_allclose(np.arctan2(rho, -np.asarray(b.q[:, 2])), np.abs(th), atol=1e-8)


def test_bead_on_rotating_parabola_both_forms():
    # ω² > 2gc: released at rest at r₀ the bead climbs outwards. Generalized form: the Jacobi
    # integral h = ½ m ṙ²(1 + 4c²r²) − ½ m ω² r² + m g c r² is conserved. Cylindrical form
    # (f = (z − c r², φ − ωt)) gives the same r(t), with φ = ωt and z = c r².
    c, w, r0 = 0.5, 3.5, 0.3
    args = {"c": c, "omega": w}
    ts = jnp.linspace(0, 0.5, 5)
    a = simulate(systems.bead_on_rotating_parabola(), [r0], [0.0], ts, args)
    r, rd = np.asarray(a.q[:, 0]), np.asarray(a.qd[:, 0])
    h = 0.5 * rd**2 * (1 + 4 * c**2 * r**2) - 0.5 * w**2 * r**2 + G * c * r**2
    assert_conserved(h)
    np.testing.assert_allclose(a.energy, h, rtol=1e-12)
    b = simulate(
        systems.bead_on_rotating_parabola("cylindrical"), [r0, 0.0, c * r0**2], [0.0, w, 0.0], ts, args
    )
    np.testing.assert_allclose(b.q[:, 0], r, rtol=1e-8)
    np.testing.assert_allclose(b.q[:, 1], w * ts, atol=1e-9)
    np.testing.assert_allclose(b.q[:, 2], c * r**2, rtol=1e-8)


@pytest.mark.parametrize("form", ["generalized", "spherical", "cartesian"])
def test_cone_circular_orbit(form):
    # Seed 002: r₀ = (l_z²/(m² g sin²α cos α))^{1/3} with φ̇ = l_z/(m r₀² sin²α) stays circular.
    m, alpha, lz = 1.3, 0.5, 2.0
    args = {"m": m, "alpha": alpha}
    r0 = (lz**2 / (m**2 * G * math.sin(alpha) ** 2 * math.cos(alpha))) ** (1 / 3)
    rate = lz / (m * r0**2 * math.sin(alpha) ** 2)
    ts = jnp.linspace(0, 1.0, 5)
    system = systems.particle_on_cone(form)
    if form == "generalized":
        traj = simulate(system, [r0, 0.0], [0.0, rate], ts, args)
        np.testing.assert_allclose(traj.q[:, 0], r0, rtol=1e-9)
        np.testing.assert_allclose(traj.momenta[:, 1], lz, rtol=1e-9)
    elif form == "spherical":
        traj = simulate(system, [r0, alpha, 0.0], [0.0, 0.0, rate], ts, args)
        np.testing.assert_allclose(traj.q[:, :2], np.tile([r0, alpha], (5, 1)), rtol=1e-9)
        np.testing.assert_allclose(traj.q[:, 2], rate * ts, rtol=1e-9)
    else:
        rho, z = r0 * math.sin(alpha), r0 * math.cos(alpha)
        traj = simulate(system, [rho, 0.0, z], [0.0, rho * rate, 0.0], ts, args)
        expected = np.stack([rho * np.cos(rate * ts), rho * np.sin(rate * ts), np.full(ts.shape, z)], -1)
        np.testing.assert_allclose(traj.q, expected, atol=1e-8)
        # The normal force balances gravity and supplies the centripetal force:
        # N = m (g sin α + ρ φ̇² cos α) (outward normal ∇f = (cos α ρ̂, −sin α) has unit length,
        # and λ = −N as the surface pushes along −∇f).
        normal = m * (G * math.sin(alpha) + rho * rate**2 * math.cos(alpha))
        np.testing.assert_allclose(traj.multipliers[:, 0], -normal, rtol=1e-9)
    assert_conserved(traj.energy)


@pytest.mark.parametrize("form", ["spherical", "cartesian"])
def test_particle_on_sphere_normal_force(form):
    # From rest at θ₀ from the top: λ = m g (3 cos θ − 2 cos θ₀) (seed 000).
    R, m, th0 = 1.5, 0.6, 0.3
    args = {"R": R, "m": m}
    ts = jnp.linspace(0, 0.5, 5)
    if form == "spherical":
        traj = simulate(systems.particle_on_sphere(), [R, th0, 0.4], [0.0, 0.0, 0.0], ts, args)
        cos_th = np.cos(np.asarray(traj.q[:, 1]))
    else:
        traj = simulate(
            systems.particle_on_sphere("cartesian"),
            [R * math.sin(th0), 0.0, R * math.cos(th0)],
            [0.0, 0.0, 0.0],
            ts,
            args,
        )
        cos_th = np.asarray(traj.q[:, 2]) / R
    assert cos_th[-1] < math.cos(th0) - 0.1  # it did slide
    np.testing.assert_allclose(traj.multipliers[:, 0], m * G * (3 * cos_th - 2 * math.cos(th0)), rtol=1e-9)
    assert_conserved(traj.energy)
    assert systems.particle_on_sphere(unilateral=True).unilateral == (0,)


def test_spiral_both_forms():
    # r = aθ, no force but the constraint: θ̈ = −θθ̇²/(1 + θ²), λ = −m a θ̇² (2θ + θ³)/(1 + θ²)
    # (seed 000); the speed a |θ̇| √(1 + θ²) is constant.
    a, m, th0, thd0 = 0.4, 1.2, 1.0, 2.0
    args = {"a": a, "m": m}
    ts = jnp.linspace(0, 0.5, 5)
    polar = simulate(systems.spiral(), [a * th0, th0], [a * thd0, thd0], ts, args)
    th, thd = np.asarray(polar.q[:, 1]), np.asarray(polar.qd[:, 1])
    np.testing.assert_allclose(polar.accelerations[:, 1], -th * thd**2 / (1 + th**2), rtol=1e-9)
    np.testing.assert_allclose(
        polar.multipliers[:, 0], -m * a * thd**2 * (2 * th + th**3) / (1 + th**2), rtol=1e-9
    )
    assert_conserved(a * np.abs(thd) * np.sqrt(1 + th**2))
    reduced = simulate(systems.spiral("generalized"), [th0], [thd0], ts, args)
    np.testing.assert_allclose(reduced.q[:, 0], th, rtol=1e-8)


# --------------------------------------------------------------------------------------------
# Fields
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("form", ["polar", "cartesian"])
def test_kepler_period(form):
    # From perihelion r_p = a(1 − e) with speed √((k/m)(1 + e)/r_p): an ellipse of semi-major
    # axis a and period T = 2π √(m a³/k); after T the state returns.
    m, k, a, e = 0.5, 2.0, 1.0, 0.3
    rp = a * (1 - e)
    v = math.sqrt(k / m * (1 + e) / rp)
    period = 2 * math.pi * math.sqrt(m * a**3 / k)
    ts = jnp.linspace(0, period, 3)
    if form == "polar":
        traj = simulate(systems.kepler(), [rp, 0.0], [0.0, v / rp], ts, {"m": m, "k": k})
        np.testing.assert_allclose(traj.q[-1], [rp, 2 * math.pi], rtol=1e-8)
        np.testing.assert_allclose(traj.momenta[:, 1], m * rp * v, rtol=1e-9)
    else:
        traj = simulate(systems.kepler("cartesian"), [rp, 0.0], [0.0, v], ts, {"m": m, "k": k})
        np.testing.assert_allclose(traj.q[-1], [rp, 0.0], atol=1e-8)
        np.testing.assert_allclose(traj.qd[-1], [0.0, v], atol=1e-8)
    np.testing.assert_allclose(traj.energy, -k / (2 * a), rtol=1e-9)


def test_charged_particle_gyration_and_drift():
    # m ẍ = e (E + ẋ × B), B = B ẑ, E = (E_x, 0, E_z): after one cyclotron period
    # T = 2π m/(eB) the in-plane motion has advanced by the drift (E × B)/B² T = (0, −E_x/B, 0) T;
    # along B it accelerates uniformly: z = ½ (e E_z/m) t².
    m, e, b, ex, ez = 2.0, 0.5, 1.5, 0.3, 0.1
    args = {"m": m, "charge": e, "B": jnp.array([0.0, 0.0, b]), "E": jnp.array([ex, 0.0, ez])}
    period = 2 * math.pi * m / (e * b)
    traj = simulate(
        systems.charged_particle(), [0.0, 0.0, 0.0], [0.4, 0.2, 0.0], jnp.linspace(0, period, 3), args
    )
    np.testing.assert_allclose(traj.q[-1], [0.0, -ex / b * period, 0.5 * e * ez / m * period**2], atol=1e-8)
    np.testing.assert_allclose(traj.qd[-1, :2], [0.4, 0.2], atol=1e-8)


# --------------------------------------------------------------------------------------------
# Rolling and skating
# --------------------------------------------------------------------------------------------


def test_rolling_disk_circles():
    # θ̇ and φ̇ constant: ẋ = Rθ̇ cos(φ̇t), ẏ = Rθ̇ sin(φ̇t), a circle of radius Rθ̇/φ̇.
    R, thd, phd = 0.5, 2.0, 0.8
    ts = jnp.linspace(0, 2.0, 5)
    traj = simulate(systems.rolling_disk(), [0.0, 0.0, 0.0, 0.0], [R * thd, 0.0, phd, thd], ts, {"R": R})
    rho = R * thd / phd
    expected = np.stack([rho * np.sin(phd * ts), rho * (1 - np.cos(phd * ts))], -1)
    np.testing.assert_allclose(traj.q[:, :2], expected, atol=1e-8)
    np.testing.assert_allclose(traj.qd[:, 2:], np.tile([phd, thd], (5, 1)), rtol=1e-9)
    assert_conserved(traj.energy)


def test_disk_on_incline():
    # Seed 001: s̈ = ⅔ g sin α, friction multiplier λ = −⅓ m g sin α.
    m, alpha = 2.0, 0.4
    ts = jnp.linspace(0, 1.0, 5)
    traj = simulate(systems.disk_on_incline(), [0.0, 0.0], [0.0, 0.0], ts, {"m": m, "alpha": alpha, "R": 0.3})
    np.testing.assert_allclose(traj.q[:, 0], G * math.sin(alpha) * ts**2 / 3, atol=1e-9)
    np.testing.assert_allclose(traj.multipliers[:, 0], -m * G * math.sin(alpha) / 3, rtol=1e-9)


def test_knife_edge_drifts_across_the_slope():
    # θ̇ = ω constant; from rest at the origin with θ(0) = 0:
    # x = (g sin α/2ω²) sin²ωt, y = (g sin α/2ω²)(ωt − ½ sin 2ωt).
    w, alpha = 2.0, 0.3
    ts = jnp.linspace(0, 1.5, 5)
    traj = simulate(systems.knife_edge(), [0.0, 0.0, 0.0], [0.0, 0.0, w], ts, {"alpha": alpha})
    amp = G * math.sin(alpha) / (2 * w**2)
    expected = np.stack([amp * np.sin(w * ts) ** 2, amp * (w * ts - 0.5 * np.sin(2 * w * ts))], -1)
    np.testing.assert_allclose(traj.q[:, :2], expected, atol=1e-8)
    np.testing.assert_allclose(traj.q[:, 2], w * ts, rtol=1e-9)
    assert_conserved(traj.energy)  # the blade's reaction does no work


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------


def test_parameters_defaults_and_errors():
    assert systems.default_args(systems.simple_pendulum) == {"m": 1.0, "l": 1.0, "g": 9.81}
    defaults = systems.default_args(systems.kepler)
    defaults["k"] = 5.0  # an editable copy
    assert systems.kepler.defaults["k"] == 1.0
    pendulum = systems.simple_pendulum()
    state = (jnp.array([0.1]), jnp.array([0.0]))
    with pytest.raises(KeyError, match="unknown parameter"):
        pendulum.check(*state, args={"G": 1.0})
    with pytest.raises(TypeError, match="dict"):
        pendulum.check(*state, args=(1.0, 2.0))
    with pytest.raises(ValueError, match="form must be one of"):
        systems.particle_on_cone("polar")
    with pytest.raises(ValueError, match="n >= 1"):
        systems.n_link_pendulum(0)
    with pytest.raises(TypeError, match="not a jaxlag.systems model"):
        systems.default_args(len)
