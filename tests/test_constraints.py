r"""Holonomic constraints: closed-form physics, drift control, initial-state projection, bad input.

Sign convention under test (DESIGN.md, seeds): ``d/dt ∂L/∂q̇ − ∂L/∂q = Jᵀλ``, i.e.
``M q̈ = F + Jᵀλ`` with ``J = ∂f/∂q``. Every expected multiplier below is re-derived in a comment
from that convention and the stated ``f``, not copied from a seed text.

Unless a test says otherwise the integration runs at the library default
``PIDController(rtol=1e-10, atol=1e-10)`` (Tsit5), so trajectory tolerances of ~1e-8 leave two
orders of magnitude for the accumulated global error over a few seconds, and state-wise identities
(a multiplier or an acceleration recomputed at a saved state) are held to ~1e-10 relative, far above
float64 rounding of the few operations involved.
"""

from __future__ import annotations

import math

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxlag as jl
from jaxlag._mechanics.kkt import solve_kkt

jax.config.update("jax_enable_x64", True)


def _controller(tol):
    return diffrax.PIDController(rtol=tol, atol=tol)


# --------------------------------------------------------------------------------------------
# Models (all Lagrangians written out here, independently of jaxlag.systems)
# --------------------------------------------------------------------------------------------


def polar_pendulum_lagrangian(q, qd, args):
    # (r, θ), θ from the downward vertical: V = −m g r cos θ.
    r, th = q
    rd, thd = qd
    m, g = args["m"], args["g"]
    return 0.5 * m * (rd**2 + r**2 * thd**2) + m * g * r * jnp.cos(th)


def rod_constraint(q, args):
    return jnp.array([q[0] - args["l"]])


def reduced_pendulum_lagrangian(q, qd, args):
    m, g, l = args["m"], args["g"], args["l"]
    return 0.5 * m * l**2 * qd[0] ** 2 + m * g * l * jnp.cos(q[0])


def cartesian_pendulum_lagrangian(q, qd, args):
    # (x, y), y up.
    return 0.5 * args["m"] * jnp.sum(qd**2) - args["m"] * args["g"] * q[1]


def circle_constraint(q, args):
    return jnp.array([q[0] ** 2 + q[1] ** 2 - args["l"] ** 2])


def sphere_lagrangian(q, qd, args):
    # (r, θ), θ from the top: V = m g r cos θ.
    r, th = q
    rd, thd = qd
    m, g = args["m"], args["g"]
    return 0.5 * m * (rd**2 + r**2 * thd**2) - m * g * r * jnp.cos(th)


def sphere_constraint(q, args):
    return jnp.array([q[0] - args["R"]])


def double_pendulum_cartesian_lagrangian(q, qd, args):
    # q = (x1, y1, x2, y2), y up.
    m1, m2, g = args["m1"], args["m2"], args["g"]
    kinetic = 0.5 * m1 * (qd[0] ** 2 + qd[1] ** 2) + 0.5 * m2 * (qd[2] ** 2 + qd[3] ** 2)
    return kinetic - m1 * g * q[1] - m2 * g * q[3]


def double_pendulum_links(q, args):
    x1, y1, x2, y2 = q
    return jnp.array(
        [
            x1**2 + y1**2 - args["l1"] ** 2,
            (x2 - x1) ** 2 + (y2 - y1) ** 2 - args["l2"] ** 2,
        ]
    )


def double_pendulum_angle_lagrangian(q, qd, args):
    # θ1, θ2 from the downward vertical, each link angle absolute.
    th1, th2 = q
    w1, w2 = qd
    m1, m2, l1, l2, g = args["m1"], args["m2"], args["l1"], args["l2"], args["g"]
    kinetic = (
        0.5 * (m1 + m2) * l1**2 * w1**2
        + 0.5 * m2 * l2**2 * w2**2
        + m2 * l1 * l2 * w1 * w2 * jnp.cos(th1 - th2)
    )
    potential = -(m1 + m2) * g * l1 * jnp.cos(th1) - m2 * g * l2 * jnp.cos(th2)
    return kinetic - potential


DP_ARGS = {"m1": 1.0, "m2": 0.7, "l1": 1.0, "l2": 0.8, "g": 9.81}


def angles_to_cartesian(th, w, args):
    """Positions and velocities of the two bobs from link angles (θ from the downward vertical)."""
    l1, l2 = args["l1"], args["l2"]
    s1, c1, s2, c2 = np.sin(th[..., 0]), np.cos(th[..., 0]), np.sin(th[..., 1]), np.cos(th[..., 1])
    x1, y1 = l1 * s1, -l1 * c1
    x2, y2 = x1 + l2 * s2, y1 - l2 * c2
    vx1, vy1 = l1 * c1 * w[..., 0], l1 * s1 * w[..., 0]
    vx2, vy2 = vx1 + l2 * c2 * w[..., 1], vy1 + l2 * s2 * w[..., 1]
    return np.stack([x1, y1, x2, y2], -1), np.stack([vx1, vy1, vx2, vy2], -1)


# --------------------------------------------------------------------------------------------
# Pendulum in polar coordinates
# --------------------------------------------------------------------------------------------


def test_polar_pendulum_matches_reduced_pendulum_and_tension():
    args = {"m": 1.3, "g": 9.81, "l": 0.9}
    system = jl.System(polar_pendulum_lagrangian, holonomic=rod_constraint)
    reduced = jl.System(reduced_pendulum_lagrangian)
    th0, w0 = 1.2, 0.5  # large amplitude: the small-angle solution would be far off
    ts = jnp.linspace(0.0, 3.0, 61)
    traj = jl.simulate(system, jnp.array([args["l"], th0]), jnp.array([0.0, w0]), ts, args=args)
    ref = jl.simulate(reduced, jnp.array([th0]), jnp.array([w0]), ts, args=args)

    # Both runs at rtol=atol=1e-10 over ~2 periods: global error ~1e-9 (measured 5e-10 in θ,
    # 1.5e-9 in θ̇); 1e-8 leaves a factor of ~6 or more.
    np.testing.assert_allclose(traj.q[:, 1], ref.q[:, 0], rtol=0, atol=1e-8)
    np.testing.assert_allclose(traj.qd[:, 1], ref.qd[:, 0], rtol=0, atol=1e-8)
    # Projection after each step puts r back on l to rounding (one Newton step, linear f: exact).
    np.testing.assert_allclose(traj.q[:, 0], args["l"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(traj.qd[:, 0], 0.0, rtol=0, atol=1e-12)

    # f = r − l, J = (1, 0). Radial equation m r̈ − m r θ̇² − m g cos θ = λ with r̈ = 0, r = l:
    #   λ = −m l θ̇² − m g cos θ   (tension pulls inward, λ < 0 at the bottom).
    m, g, l = args["m"], args["g"], args["l"]
    th, thd = traj.q[:, 1], traj.qd[:, 1]
    expected = -m * l * thd**2 - m * g * jnp.cos(th)
    lam = traj.multipliers[:, 0]
    # State-wise identity: only rounding of O(10) operations on O(10)-sized terms.
    np.testing.assert_allclose(lam, expected, rtol=1e-11, atol=1e-11)
    # And against the independently integrated reduced solution (global error as above, × m l |2θ̇|).
    expected_ref = -m * l * ref.qd[:, 0] ** 2 - m * g * jnp.cos(ref.q[:, 0])
    np.testing.assert_allclose(lam, expected_ref, rtol=0, atol=1e-7)
    # Constraint force is Jᵀλ: all radial.
    np.testing.assert_allclose(traj.constraint_forces[:, 0], lam, rtol=1e-14, atol=0)
    np.testing.assert_allclose(traj.constraint_forces[:, 1], 0.0, atol=1e-14)


# --------------------------------------------------------------------------------------------
# Particle on an Archimedean spiral
# --------------------------------------------------------------------------------------------


def test_particle_on_archimedean_spiral():
    a, m = 0.5, 2.0
    args = {"a": a, "m": m}

    def lagrangian(q, qd, args):
        r, th = q
        rd, thd = qd
        return 0.5 * args["m"] * (rd**2 + r**2 * thd**2)

    def spiral(q, args):
        return jnp.array([q[0] - args["a"] * q[1]])

    system = jl.System(lagrangian, holonomic=spiral)
    th0, w0 = 1.0, 1.3
    ts = jnp.linspace(0.0, 3.0, 31)
    traj = jl.simulate(system, jnp.array([a * th0, th0]), jnp.array([a * w0, w0]), ts, args=args)
    th, thd = traj.q[:, 1], traj.qd[:, 1]

    # Re-derivation with f = r − aθ, J = (1, −a), M q̈ = F + Jᵀλ:
    #   r:  m r̈ − m r θ̇² = λ
    #   θ:  d/dt(m r² θ̇) = −a λ
    # With r = aθ: λ = m a (θ̈ − θ θ̇²) = −m a (θ² θ̈ + 2 θ θ̇²), so
    #   θ̈ = −θ θ̇² / (1 + θ²),   λ = −(2θ + θ³) m a θ̇² / (1 + θ²).
    # This is exactly the formula: with this f (not aθ − r) the library's λ has the
    # issue's sign; λ < 0 means the wire pushes the particle towards smaller r (centripetal).
    thdd_expected = -th * thd**2 / (1 + th**2)
    lam_expected = -(2 * th + th**3) * m * a * thd**2 / (1 + th**2)
    # State-wise identities: rounding only.
    np.testing.assert_allclose(traj.accelerations[:, 1], thdd_expected, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(traj.multipliers[:, 0], lam_expected, rtol=1e-11, atol=1e-12)
    assert bool(jnp.all(traj.multipliers[:, 0] < 0))

    # Closed-form motion: energy ½ m a² θ̇² (1 + θ²) is conserved, so θ̇ √(1+θ²) = C and
    #   G(θ) − G(θ0) = C t  with  G(θ) = ½ (θ √(1+θ²) + asinh θ).
    c = w0 * math.sqrt(1 + th0**2)
    big_g = 0.5 * (th * jnp.sqrt(1 + th**2) + jnp.arcsinh(th))
    g0 = 0.5 * (th0 * math.sqrt(1 + th0**2) + math.asinh(th0))
    # Global error of a 3 s run at rtol 1e-10 on |G| ≲ 10: ≲ 1e-9 (measured 7e-10); 1e-8 margin.
    np.testing.assert_allclose(big_g - g0, c * ts, rtol=0, atol=1e-8)
    # Energy error of the integrator, ~1e-10 per unit time (measured 7e-10 relative): 1e-8.
    np.testing.assert_allclose(thd * jnp.sqrt(1 + th**2), c, rtol=1e-8)


# --------------------------------------------------------------------------------------------
# Particle sliding on a sphere
# --------------------------------------------------------------------------------------------

SPHERE_ARGS = {"m": 1.5, "g": 9.81, "R": 2.0}
SPHERE_TS = jnp.linspace(0.0, 1.6, 81)


def _sphere_run(th0, args, ts, tol=1e-10):
    system = jl.System(sphere_lagrangian, holonomic=sphere_constraint)
    q0 = jnp.stack([jnp.asarray(args["R"], float), jnp.asarray(th0, float)])
    return jl.simulate(system, q0, jnp.zeros(2), ts, args=args, stepsize_controller=_controller(tol))


def test_particle_on_sphere_normal_force_and_release_angle():
    args = SPHERE_ARGS
    m, g, big_r = args["m"], args["g"], args["R"]
    system = jl.System(sphere_lagrangian, holonomic=sphere_constraint)
    th0 = 0.1
    q0, qd0 = jnp.array([big_r, th0]), jnp.zeros(2)
    ts = SPHERE_TS  # leaves the sphere at t ≈ 1.3; the (bilateral) constraint continues
    traj = _sphere_run(th0, args, ts)

    # f = r − R, J = (1, 0): m r̈ − m r θ̇² + m g cos θ = λ, with r̈ = 0 and energy
    # m R θ̇² = 2 m g (cos θ0 − cos θ):  λ = m g (3 cos θ − 2 cos θ0)  (> 0: the surface pushes out).
    expected = m * g * (3 * jnp.cos(traj.q[:, 1]) - 2 * math.cos(th0))
    # λ = m g cos θ − m R θ̇² is exact at each state, so the check measures how well the run keeps
    # energy: an energy error ΔE changes λ by 2ΔE/R; ΔE ~ 1e-10 × m g R ≈ 3e-9 at rtol 1e-10
    # (measured Δλ 4.6e-9). 5e-8 absolute (λ is O(15)) leaves a factor of 10.
    np.testing.assert_allclose(traj.multipliers[:, 0], expected, rtol=0, atol=5e-8)
    assert float(traj.multipliers[0, 0]) > 0 and float(traj.multipliers[-1, 0]) < 0

    # Release point by a diffrax event on λ(t) = 0 (passed through simulate unchanged).
    def normal_force(t, y, args, **kwargs):
        return system.multipliers(y[0], y[1], t, args)[0]

    event = diffrax.Event(normal_force, root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
    hit = jl.simulate(system, q0, qd0, t0=0.0, t1=5.0, args=args, event=event, saveat=diffrax.SaveAt(t1=True))
    th_release = hit.q[-1, 1]
    assert 0.5 < float(hit.t[-1]) < 5.0
    # Root found to 1e-12 in t on an interpolant with local error ~1e-10: cos θ to ≲ 1e-9.
    np.testing.assert_allclose(jnp.cos(th_release), 2.0 / 3.0 * math.cos(th0), rtol=0, atol=1e-9)
    np.testing.assert_allclose(hit.multipliers[-1, 0], 0.0, atol=1e-8)


# --------------------------------------------------------------------------------------------
# Disk rolling down an incline
# --------------------------------------------------------------------------------------------


def test_disk_rolling_down_incline():
    args = {"m": 2.0, "R": 0.3, "g": 9.81, "alpha": 0.4}
    m, big_r, g, alpha = args["m"], args["R"], args["g"], args["alpha"]

    def lagrangian(q, qd, args):
        y, phi = q
        yd, phid = qd
        return (
            0.5 * args["m"] * yd**2
            + 0.25 * args["m"] * args["R"] ** 2 * phid**2
            + args["m"] * args["g"] * y * jnp.sin(args["alpha"])
        )

    def rolling(q, args):
        return jnp.array([q[0] - args["R"] * q[1]])

    system = jl.System(lagrangian, holonomic=rolling)
    v0 = 0.5
    ts = jnp.linspace(0.0, 2.0, 21)
    traj = jl.simulate(system, jnp.zeros(2), jnp.array([v0, v0 / big_r]), ts, args=args)

    # f = y − Rφ, J = (1, −R):
    #   y:  m ÿ − m g sin α = λ
    #   φ:  ½ m R² φ̈ = −R λ,  φ̈ = ÿ / R  ⇒  λ = −½ m ÿ
    #   ⇒ ÿ = (2/3) g sin α,  λ = −(1/3) m g sin α.
    # Generalized constraint forces Jᵀλ: Q_y = λ = −(1/3) m g sin α (friction, up the slope) and
    # Q_φ = −R λ = +(1/3) m R g sin α (the friction torque that spins the disk up), as in the issue.
    s = math.sin(alpha)
    # Constant accelerations: state-wise, rounding only.
    np.testing.assert_allclose(traj.accelerations[:, 0], 2.0 / 3.0 * g * s, rtol=1e-12)
    np.testing.assert_allclose(traj.accelerations[:, 1], 2.0 / 3.0 * g * s / big_r, rtol=1e-12)
    np.testing.assert_allclose(traj.multipliers[:, 0], -m * g * s / 3.0, rtol=1e-12)
    np.testing.assert_allclose(traj.constraint_forces[:, 0], -m * g * s / 3.0, rtol=1e-12)
    np.testing.assert_allclose(traj.constraint_forces[:, 1], m * big_r * g * s / 3.0, rtol=1e-12)
    # A quadratic in t is integrated exactly by a 5th-order method: rounding-level agreement.
    y_exact = v0 * ts + g * s / 3.0 * ts**2
    np.testing.assert_allclose(traj.q[:, 0], y_exact, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(traj.q[:, 1], y_exact / big_r, rtol=1e-12, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Double pendulum: Cartesian with two distance constraints vs generalized angles
# --------------------------------------------------------------------------------------------


def test_cartesian_double_pendulum_matches_angle_formulation():
    args = DP_ARGS
    cartesian = jl.System(double_pendulum_cartesian_lagrangian, holonomic=double_pendulum_links)
    angles = jl.System(double_pendulum_angle_lagrangian)
    th0, w0 = np.array([1.0, -0.6]), np.array([0.3, 1.1])
    x0, v0 = angles_to_cartesian(th0, w0, args)
    ts = jnp.linspace(0.0, 3.0, 31)
    traj_c = jl.simulate(cartesian, x0, v0, ts, args=args)
    traj_a = jl.simulate(angles, th0, w0, ts, args=args)
    x_ref, v_ref = angles_to_cartesian(np.asarray(traj_a.q), np.asarray(traj_a.qd), args)
    # Two different formulations each at rtol 1e-10 over 3 s of an irregular motion: measured
    # discrepancy 3.4e-10 (positions) and 1.6e-9 (velocities); 1e-8 keeps a factor of ≥ 6.
    np.testing.assert_allclose(traj_c.q, x_ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(traj_c.qd, v_ref, rtol=0, atol=1e-8)
    f, f_dot, _ = traj_c.constraint_residuals
    np.testing.assert_allclose(f, 0.0, atol=1e-12)  # projected every step and at every save
    np.testing.assert_allclose(f_dot, 0.0, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Rheonomic constraint: bead on a wire rotating at constant ω in a horizontal plane
# --------------------------------------------------------------------------------------------


def test_bead_on_rotating_wire():
    args = {"m": 0.8, "omega": 1.5}
    m, w = args["m"], args["omega"]

    def lagrangian(q, qd, args):
        return 0.5 * args["m"] * jnp.sum(qd**2)

    def on_wire(q, t, args):
        wt = args["omega"] * t
        return jnp.array([-q[0] * jnp.sin(wt) + q[1] * jnp.cos(wt)])

    system = jl.System(lagrangian, holonomic=on_wire)
    r0 = 0.4
    # At rest in the rotating frame: velocity r0 ω along ê_θ = (0, 1) at t = 0.
    q0, qd0 = jnp.array([r0, 0.0]), jnp.array([0.0, r0 * w])
    ts = jnp.linspace(0.0, 2.0, 41)
    traj = jl.simulate(system, q0, qd0, ts, args=args)

    # Position r ê_r with ê_r = (cos ωt, sin ωt); J = (−sin ωt, cos ωt) = ê_θ. In polar form the
    # acceleration is (r̈ − r ω²) ê_r + 2 ṙ ω ê_θ, and m a = Jᵀλ = λ ê_θ gives
    #   r̈ = ω² r  ⇒  r = r0 cosh ωt (from ṙ(0) = 0),   λ = 2 m ω ṙ = 2 m ω² r0 sinh ωt  (> 0:
    # the wire pushes the bead forward, in the direction of rotation).
    r_exact = r0 * jnp.cosh(w * ts)
    x_exact = r_exact * jnp.cos(w * ts)
    y_exact = r_exact * jnp.sin(w * ts)
    # cosh grows to ≈ 10: relative global error ~1e-9 at rtol 1e-10; 1e-8 relative to r.
    np.testing.assert_allclose(traj.q[:, 0], x_exact, rtol=0, atol=1e-8 * float(r_exact[-1]))
    np.testing.assert_allclose(traj.q[:, 1], y_exact, rtol=0, atol=1e-8 * float(r_exact[-1]))
    r = jnp.linalg.norm(traj.q, axis=1)
    rdot = jnp.sum(traj.q * traj.qd, axis=1) / r  # radial velocity of the saved state
    lam = traj.multipliers[:, 0]
    # State-wise identity λ = 2 m ω ṙ: rounding only (measured 7e-15).
    np.testing.assert_allclose(lam, 2 * m * w * rdot, rtol=1e-11, atol=1e-12)
    # Against the closed form in time (global error, relative 1e-8 as above).
    np.testing.assert_allclose(lam, 2 * m * w**2 * r0 * jnp.sinh(w * ts), rtol=1e-8, atol=1e-10)
    f, f_dot, _ = traj.constraint_residuals
    np.testing.assert_allclose(f, 0.0, atol=1e-12)
    np.testing.assert_allclose(f_dot, 0.0, atol=1e-12)  # includes ∂f/∂t


# --------------------------------------------------------------------------------------------
# Drift: 1000 periods of a Cartesian pendulum
# --------------------------------------------------------------------------------------------


def test_drift_over_1000_periods(capsys):
    args = {"m": 1.0, "g": 9.81, "l": 1.0}
    system = jl.System(cartesian_pendulum_lagrangian, holonomic=circle_constraint)
    th0 = 1.0
    q0 = jnp.array([math.sin(th0), -math.cos(th0)])
    qd0 = jnp.zeros(2)
    period = 2 * math.pi * math.sqrt(args["l"] / args["g"])  # small-angle; only sets the horizon
    ts = jnp.linspace(0.0, 1000 * period, 2001)
    common = dict(args=args, max_steps=2**20)  # ~170k Tsit5 steps at rtol 1e-10 (~0.5 s each run)

    results = {}
    for name, options in [
        ("projection (default)", {}),
        ("projection=None", {"projection": None}),
        ("Baumgarte(10, 10), no projection", {"projection": None, "baumgarte": jl.Baumgarte(10.0, 10.0)}),
    ]:
        traj = jl.simulate(system, q0, qd0, ts, **common, **options)
        f, f_dot, _ = traj.constraint_residuals
        energy = traj.energy
        results[name] = (
            float(jnp.max(jnp.abs(f))),
            float(jnp.max(jnp.abs(f_dot))),
            float(jnp.max(jnp.abs(energy - energy[0]))),
            int(traj.stats["num_steps"]),
        )
    with capsys.disabled():
        print("\n[drift] Cartesian pendulum, θ0 = 1 rad, 1000 periods (2006 s), Tsit5 rtol=atol=1e-10")
        for name, (f_max, fd_max, e_max, steps) in results.items():
            print(
                f"[drift]   {name:34s} max|f| = {f_max:.2e}  max|ḟ| = {fd_max:.2e}  "
                f"max|Δh| = {e_max:.2e}  steps = {steps}"
            )

    # The promise: the default projection holds the manifold to 1e-10 (measured: rounding, 2e-16).
    assert results["projection (default)"][0] <= 1e-10
    assert results["projection (default)"][1] <= 1e-10
    # Loose bounds that document the alternatives (measured 2.8e-4 and 6.5e-11): the index-1
    # formulation alone drifts linearly in time; Baumgarte feedback holds it near the local error.
    assert results["projection=None"][0] <= 1e-2
    assert results["Baumgarte(10, 10), no projection"][0] <= 1e-8


# --------------------------------------------------------------------------------------------
# consistent_initial_state
# --------------------------------------------------------------------------------------------


def test_consistent_initial_state_reaches_manifold():
    args = DP_ARGS
    system = jl.System(double_pendulum_cartesian_lagrangian, holonomic=double_pendulum_links)
    x0, v0 = angles_to_cartesian(np.array([0.7, -0.4]), np.array([1.0, -2.0]), args)
    rng = np.random.default_rng(0)
    q_bad = x0 + 0.05 * rng.standard_normal(4)
    qd_bad = v0 + 0.5 * rng.standard_normal(4)
    q, qd = jl.consistent_initial_state(system, q_bad, qd_bad, 0.0, args)
    f, f_dot, _ = system.constraint_residuals(q, qd, 0.0, args)
    # 20 Newton steps converge quadratically to rounding; velocity projection is linear and exact.
    assert float(jnp.max(jnp.abs(f))) <= 1e-12
    assert float(jnp.max(jnp.abs(f_dot))) <= 1e-12


def test_consistent_initial_state_rheonomic_uses_t0():
    # Bead on the rotating wire at t0 = 0.7: ḟ = J q̇ + ∂f/∂t must vanish, not just J q̇.
    def lagrangian(q, qd):
        return 0.5 * jnp.sum(qd**2)

    def on_wire(q, t):
        return jnp.array([-q[0] * jnp.sin(2.0 * t) + q[1] * jnp.cos(2.0 * t)])

    system = jl.System(lagrangian, holonomic=on_wire)
    t0 = 0.7
    q, qd = jl.consistent_initial_state(system, jnp.array([1.0, 0.3]), jnp.array([0.2, 0.1]), t0)
    f, f_dot, _ = system.constraint_residuals(q, qd, t0)
    assert float(jnp.max(jnp.abs(f))) <= 1e-12
    assert float(jnp.max(jnp.abs(f_dot))) <= 1e-12
    # Linear constraint: the position projection is exactly the M-orthogonal (here Euclidean) one.
    n = jnp.array([-math.sin(2 * t0), math.cos(2 * t0)])
    np.testing.assert_allclose(q, jnp.array([1.0, 0.3]) - (n @ jnp.array([1.0, 0.3])) * n, atol=1e-14)


def test_consistent_initial_state_is_mass_weighted_minimal():
    # Anisotropic masses on a straight line x + 2y = 1 (linear f, so the projection is exact):
    # minimise ½ Δqᵀ M Δq subject to J (q + Δq) = b  ⇒  Δq = −M⁻¹Jᵀ (J M⁻¹ Jᵀ)⁻¹ f(q);
    # the same formula, with the velocity residual J q̇, gives the velocity correction.
    m1, m2 = 3.0, 0.5

    def lagrangian(q, qd):
        return 0.5 * (m1 * qd[0] ** 2 + m2 * qd[1] ** 2)

    def line(q):
        return jnp.array([q[0] + 2.0 * q[1] - 1.0])

    system = jl.System(lagrangian, holonomic=line)
    q_bad, qd_bad = np.array([0.4, 0.6]), np.array([1.0, -0.2])
    q, qd = jl.consistent_initial_state(system, q_bad, qd_bad)

    minv_jt = np.array([1.0 / m1, 2.0 / m2])
    schur = 1.0 / m1 + 4.0 / m2
    f = q_bad[0] + 2 * q_bad[1] - 1.0
    q_hand = q_bad - minv_jt * f / schur
    qd_hand = qd_bad - minv_jt * (qd_bad[0] + 2 * qd_bad[1]) / schur
    # Closed form, a handful of flops: rounding only.
    np.testing.assert_allclose(q, q_hand, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(qd, qd_hand, rtol=1e-14, atol=1e-15)
    # Minimality, checked directly: any other point on the line is farther in the M-metric.
    mass = np.diag([m1, m2])
    base = (np.asarray(q) - q_bad) @ mass @ (np.asarray(q) - q_bad)
    tangent = np.array([2.0, -1.0])
    for s in (-1e-3, 1e-3):
        other = np.asarray(q) + s * tangent - q_bad
        assert other @ mass @ other > base

    # Isotropic mass on a circle: the minimal correction is the radial one, q l/|q|, and the
    # velocity keeps only its tangential part.
    system = jl.System(cartesian_pendulum_lagrangian, holonomic=circle_constraint)
    args = {"m": 2.0, "g": 9.81, "l": 1.5}
    q_bad, qd_bad = np.array([0.9, -1.1]), np.array([0.7, 0.4])
    q, qd = jl.consistent_initial_state(system, q_bad, qd_bad, 0.0, args)
    radial = q_bad / np.linalg.norm(q_bad)
    np.testing.assert_allclose(q, args["l"] * radial, rtol=1e-13)  # Newton converged: rounding
    np.testing.assert_allclose(qd, qd_bad - (qd_bad @ radial) * radial, rtol=1e-13, atol=1e-15)


def test_consistent_initial_state_nonlinear_anisotropic_is_minimal_to_first_order():
    # Unit circle with M = diag(3, 0.5). The exact M-minimal point q* solves M(q* − q̃) = 2μ q*,
    # |q*| = 1, i.e. q*_i = M_i q̃_i / (M_i − 2μ). Newton with the metric frozen at q̃ is minimal
    # only to first order: its gap to q* is O(δ²) for a perturbation of size δ.
    from scipy.optimize import brentq

    masses = np.array([3.0, 0.5])

    def lagrangian(q, qd):
        return 0.5 * (masses[0] * qd[0] ** 2 + masses[1] * qd[1] ** 2)

    def unit_circle(q):
        return jnp.array([q[0] ** 2 + q[1] ** 2 - 1.0])

    system = jl.System(lagrangian, holonomic=unit_circle)
    delta = 1e-3
    q_bad = np.array([math.cos(0.6), math.sin(0.6)]) + delta * np.array([0.6, -0.8])
    q, _ = jl.consistent_initial_state(system, q_bad, np.zeros(2))
    mu = brentq(lambda mu: np.sum((masses * q_bad / (masses - 2 * mu)) ** 2) - 1.0, -1.0, 0.2, xtol=1e-15)
    q_star = masses * q_bad / (masses - 2 * mu)
    # Measured gap 1.6e-9 = 1.6e-3 δ²; the bound 1e-2 δ² = 1e-8 still fails any correction that
    # is wrong at first order (which would be off by ~δ = 1e-3).
    assert np.linalg.norm(np.asarray(q) - q_star) <= 1e-2 * delta**2


# --------------------------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------------------------

PENDULUM_ARGS = {"m": 1.0, "g": 9.81, "l": 1.0}


def test_off_manifold_initial_state_raises_with_pointer():
    system = jl.System(cartesian_pendulum_lagrangian, holonomic=circle_constraint)
    with pytest.raises(ValueError, match="consistent_initial_state"):
        jl.simulate(system, jnp.array([0.5, -0.7]), jnp.zeros(2), jnp.array([0.0, 1.0]), args=PENDULUM_ARGS)
    # Off the velocity level only (on the circle, velocity radial).
    with pytest.raises(ValueError, match="consistent_initial_state"):
        jl.simulate(
            system, jnp.array([0.0, -1.0]), jnp.array([0.0, 0.3]), jnp.array([0.0, 1.0]), args=PENDULUM_ARGS
        )


def test_off_manifold_initial_state_raises_under_jit():
    system = jl.System(cartesian_pendulum_lagrangian, holonomic=circle_constraint)

    @jax.jit
    def final_position(q0):
        return jl.simulate(system, q0, jnp.zeros(2), jnp.array([0.0, 0.5]), args=PENDULUM_ARGS).q

    final_position(jnp.array([0.6, -0.8])).block_until_ready()  # on the manifold: fine
    with pytest.raises(Exception, match="consistent_initial_state"):
        final_position(jnp.array([0.5, -0.7])).block_until_ready()


def test_redundant_constraints_name_the_dependent_row():
    args = DP_ARGS
    x0, v0 = angles_to_cartesian(np.array([0.7, -0.4]), np.array([1.0, -2.0]), args)

    def links_and_their_sum(q, args):
        f = double_pendulum_links(q, args)
        return jnp.concatenate([f, f[:1] + f[1:]])  # row 2 = row 0 + row 1

    system = jl.System(double_pendulum_cartesian_lagrangian, holonomic=links_and_their_sum)
    with pytest.raises(ValueError, match=r"dependent rows: holonomic\[2\]"):
        jl.simulate(system, x0, v0, jnp.array([0.0, 0.1]), args=args)

    def twice(q, args):
        return jnp.concatenate([circle_constraint(q, args), circle_constraint(q, args)])

    system = jl.System(cartesian_pendulum_lagrangian, holonomic=twice)
    with pytest.raises(ValueError, match=r"dependent rows: holonomic\[1\]"):
        jl.simulate(system, jnp.array([0.6, -0.8]), jnp.zeros(2), jnp.array([0.0, 0.1]), args=PENDULUM_ARGS)


def test_least_squares_simulates_consistent_redundant_constraints():
    def twice(q, args):
        return jnp.concatenate([circle_constraint(q, args), circle_constraint(q, args)])

    single = jl.System(cartesian_pendulum_lagrangian, holonomic=circle_constraint)
    doubled = jl.System(cartesian_pendulum_lagrangian, holonomic=twice, least_squares=True)
    q0, qd0 = jnp.array([0.6, -0.8]), jnp.array([0.8, 0.6])
    ts = jnp.linspace(0.0, 2.0, 21)
    a = jl.simulate(single, q0, qd0, ts, args=PENDULUM_ARGS)
    b = jl.simulate(doubled, q0, qd0, ts, args=PENDULUM_ARGS)
    # Same equations, different linear algebra (eigh pseudo-inverse vs Cholesky): the accelerations
    # differ by rounding, which the adaptive integration carries to ≲ 1e-14 over 2 s (measured
    # 3e-16 in q, 7e-16 in q̇; the step sequence is the same): 1e-12.
    np.testing.assert_allclose(b.q, a.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.qd, a.qd, rtol=0, atol=1e-12)
    # Minimum-norm multipliers split the single tension evenly; the total force is unchanged.
    # λ is O(10): 1e-12 is ~100 ulp for the eigendecomposition-based pseudo-inverse.
    lam = a.multipliers[:, 0]
    np.testing.assert_allclose(b.multipliers, jnp.stack([lam, lam], 1) / 2, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.constraint_forces, a.constraint_forces, rtol=0, atol=1e-12)


def test_scalar_constraint_function_raises():
    def scalar(q, args):
        return q[0] ** 2 + q[1] ** 2 - args["l"] ** 2

    system = jl.System(cartesian_pendulum_lagrangian, holonomic=scalar)
    with pytest.raises(ValueError, match=r"jnp\.array\(\[f\]\)"):
        jl.simulate(system, jnp.array([0.6, -0.8]), jnp.zeros(2), jnp.array([0.0, 0.1]), args=PENDULUM_ARGS)


# --------------------------------------------------------------------------------------------
# jit / vmap / grad
# --------------------------------------------------------------------------------------------


def test_vmap_and_jit_over_sphere_starting_angles_equal_loop():
    ts = SPHERE_TS  # same shapes and options as the sphere test: the loop reuses its compilation
    th0s = jnp.array([0.05, 0.2, 0.4, 0.7])
    batched = jax.vmap(lambda th: _sphere_run(th, SPHERE_ARGS, ts))(th0s)
    assert batched.q.shape == (4, ts.shape[0], 2)
    looped = [_sphere_run(float(th), SPHERE_ARGS, ts) for th in th0s]
    # Each batch element keeps its own adaptive step sequence; batched and scalar kernels differ
    # at most in rounding (measured 4e-16): 1e-12 bounds what rounding accumulates over the run.
    np.testing.assert_allclose(batched.q, jnp.stack([t.q for t in looped]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        batched.multipliers, jnp.stack([t.multipliers for t in looped]), rtol=0, atol=1e-11
    )  # λ is O(30): rounding (measured 2e-14)
    # Batched derived quantities still obey the closed form λ = m g (3 cos θ − 2 cos θ0)
    # (energy-error argument of the sphere test: 5e-8).
    m, g = SPHERE_ARGS["m"], SPHERE_ARGS["g"]
    expected = m * g * (3 * jnp.cos(batched.q[..., 1]) - 2 * jnp.cos(th0s)[:, None])
    np.testing.assert_allclose(batched.multipliers[..., 0], expected, rtol=0, atol=5e-8)
    jitted = jax.jit(lambda th: _sphere_run(th, SPHERE_ARGS, ts).q)(th0s[2])
    np.testing.assert_allclose(jitted, looped[2].q, rtol=0, atol=1e-12)  # same argument as vmap


def test_grad_of_constrained_trajectory_matches_finite_differences_and_scaling():
    ts = jnp.array([0.0, 0.6])
    th0 = 0.3
    tol = 1e-12

    def final_angle(params):
        args = {"m": 1.5, "g": params["g"], "R": params["R"]}
        return _sphere_run(th0, args, ts, tol).q[-1, 1]

    params = {"g": jnp.asarray(9.81), "R": jnp.asarray(2.0)}
    grads = jax.grad(final_angle)(params)

    # Central differences of an rtol=1e-12 solve with h = 1e-4 relative: truncation h²|θ'''|/6
    # ~1e-9 and solver noise ~1e-12/h ~ 1e-8, both well below the 1e-6 asked for (measured 1e-8).
    for key in ("g", "R"):
        h = 1e-4 * float(params[key])
        plus = dict(params, **{key: params[key] + h})
        minus = dict(params, **{key: params[key] - h})
        fd = (final_angle(plus) - final_angle(minus)) / (2 * h)
        np.testing.assert_allclose(grads[key], fd, rtol=1e-6)

    # Exact check: from rest, θ(t) = Θ(t √(g/R)), so ∂θ/∂g = θ̇ t / (2g) and ∂θ/∂R = −θ̇ t / (2R).
    t1 = float(ts[-1])
    args = {"m": 1.5, "g": params["g"], "R": params["R"]}
    thd = _sphere_run(th0, args, ts, tol).qd[-1, 1]
    # Identity holds to the solver's global error (rtol 1e-12 ⇒ ≲ 1e-10 relative; measured
    # 1e-13); 1e-8 margin.
    np.testing.assert_allclose(grads["g"], thd * t1 / (2 * params["g"]), rtol=1e-8)
    np.testing.assert_allclose(grads["R"], -thd * t1 / (2 * params["R"]), rtol=1e-8)


# --------------------------------------------------------------------------------------------
# Property: the KKT solve for random Cartesian double-pendulum states
# --------------------------------------------------------------------------------------------

_KKT_SYSTEM = jl.System(double_pendulum_cartesian_lagrangian, holonomic=double_pendulum_links)


@jax.jit
def _kkt_at(q, qd, args):
    return _KKT_SYSTEM.accelerations(q, qd, 0.0, args), _KKT_SYSTEM.multipliers(q, qd, 0.0, args)


def _angle_accelerations(th, w, args):
    """Closed-form double-pendulum θ̈ (θ from the downward vertical, absolute link angles)."""
    m1, m2, l1, l2, g = args["m1"], args["m2"], args["l1"], args["l2"], args["g"]
    t1, t2 = th
    w1, w2 = w
    d = t1 - t2
    den = 2 * m1 + m2 - m2 * math.cos(2 * d)
    a1 = (
        -g * (2 * m1 + m2) * math.sin(t1)
        - m2 * g * math.sin(t1 - 2 * t2)
        - 2 * math.sin(d) * m2 * (w2**2 * l2 + w1**2 * l1 * math.cos(d))
    ) / (l1 * den)
    a2 = (
        2
        * math.sin(d)
        * (w1**2 * l1 * (m1 + m2) + g * (m1 + m2) * math.cos(t1) + w2**2 * l2 * m2 * math.cos(d))
    ) / (l2 * den)
    return a1, a2


@settings(max_examples=10, deadline=None)
@given(
    th1=st.floats(-math.pi, math.pi),
    th2=st.floats(-math.pi, math.pi),
    w1=st.floats(-4.0, 4.0),
    w2=st.floats(-4.0, 4.0),
    m1=st.floats(0.2, 3.0),
    m2=st.floats(0.2, 3.0),
    l1=st.floats(0.3, 2.0),
    l2=st.floats(0.3, 2.0),
)
def test_kkt_accelerations_satisfy_constraints_and_equations(th1, th2, w1, w2, m1, m2, l1, l2):
    args = {"m1": m1, "m2": m2, "l1": l1, "l2": l2, "g": 9.81}
    q, qd = angles_to_cartesian(np.array([th1, th2]), np.array([w1, w2]), args)
    qdd, lam = _kkt_at(jnp.asarray(q), jnp.asarray(qd), args)
    qdd, lam = np.asarray(qdd), np.asarray(lam)

    # Hand-written M, F, J and γ for f1 = x1²+y1²−l1², f2 = |x2−x1|²−l2² (γ = q̇ᵀ ∂²f q̇).
    x1, y1, x2, y2 = q
    vx1, vy1, vx2, vy2 = qd
    dx, dy, dvx, dvy = x2 - x1, y2 - y1, vx2 - vx1, vy2 - vy1
    mass = np.diag([m1, m1, m2, m2])
    force = np.array([0.0, -m1 * 9.81, 0.0, -m2 * 9.81])
    jac = 2 * np.array([[x1, y1, 0, 0], [-dx, -dy, dx, dy]])
    gamma = 2 * np.array([vx1**2 + vy1**2, dvx**2 + dvy**2])

    # Terms are O(|q̇|² ≲ 100) and O(m g ≲ 30); a solve of a 4+2 system in float64 leaves
    # residuals ~1e-13: 1e-10 is the required bound with ample margin.
    np.testing.assert_allclose(jac @ qdd, -gamma, rtol=0, atol=1e-10)
    np.testing.assert_allclose(mass @ qdd - force - jac.T @ lam, 0.0, atol=1e-10)

    # Independent check of the motion itself: the Cartesian accelerations are the second
    # derivative of the angle parametrisation, with θ̈ from the closed-form double pendulum.
    # The closed form divides by 2m1 + m2 − m2 cos 2Δ ≥ 2 m1 ≥ 0.4: rounding stays ≲ 1e-12.
    a1, a2 = _angle_accelerations((th1, th2), (w1, w2), args)
    s1, c1, s2, c2 = math.sin(th1), math.cos(th1), math.sin(th2), math.cos(th2)
    ax1 = l1 * (a1 * c1 - w1**2 * s1)
    ay1 = l1 * (a1 * s1 + w1**2 * c1)
    ax2 = ax1 + l2 * (a2 * c2 - w2**2 * s2)
    ay2 = ay1 + l2 * (a2 * s2 + w2**2 * c2)
    np.testing.assert_allclose(qdd, [ax1, ay1, ax2, ay2], rtol=0, atol=1e-9)


def test_declared_diagonal_mass_matrix_gives_the_same_motion():
    """diagonal_mass=True replaces the Cholesky of M by a division; the motion is unchanged."""

    def lagrangian(q, qd):
        return 0.5 * (1.3 * (qd[0] ** 2 + qd[1] ** 2) + 0.7 * (qd[2] ** 2 + qd[3] ** 2)) - 9.81 * (
            1.3 * q[1] + 0.7 * q[3]
        )

    def rods(q):
        return jnp.array([q[0] ** 2 + q[1] ** 2 - 1.0, (q[2] - q[0]) ** 2 + (q[3] - q[1]) ** 2 - 1.0])

    q0 = jnp.array([1.0, 0.0, 1.0, -1.0])
    ts = jnp.linspace(0.0, 2.0, 11)
    dense = jl.simulate(jl.System(lagrangian, holonomic=rods), q0, jnp.zeros(4), ts)
    diagonal = jl.simulate(jl.System(lagrangian, holonomic=rods, diagonal_mass=True), q0, jnp.zeros(4), ts)
    # Same equations, different (exact) linear algebra: round-off amplified by the solver.
    np.testing.assert_allclose(diagonal.q, dense.q, atol=1e-9)
    np.testing.assert_allclose(diagonal.multipliers, dense.multipliers, atol=1e-8)


def test_declared_diagonal_mass_that_is_not_diagonal_is_an_error():
    def lagrangian(q, qd):
        return 0.5 * (qd[0] ** 2 + qd[1] ** 2) + 0.1 * qd[0] * qd[1]

    with pytest.raises(ValueError, match="diagonal_mass"):
        jl.simulate(
            jl.System(lagrangian, diagonal_mass=True), jnp.zeros(2), jnp.ones(2), jnp.linspace(0.0, 1.0, 3)
        )


def test_solve_kkt_accepts_a_matrix_or_a_solver():
    # M q̈ = F + Jᵀλ, J q̈ = c for a random SPD M: the residuals of both equations vanish, and
    # passing M, a factored solver, or declaring a diagonal M all give the same answer.
    rng = np.random.default_rng(3)
    a = rng.normal(size=(5, 5))
    mass = jnp.asarray(a @ a.T + 5 * np.eye(5))
    force, rows, rhs = (jnp.asarray(rng.normal(size=s)) for s in ((5,), (2, 5), (2,)))
    qdd, lam = solve_kkt(mass, force, rows, rhs)
    np.testing.assert_allclose(mass @ qdd, force + rows.T @ lam, atol=1e-12)
    np.testing.assert_allclose(rows @ qdd, rhs, atol=1e-12)
    from jaxlag._mechanics.linalg import spd_solver

    qdd2, lam2 = solve_kkt(spd_solver(mass), force, rows, rhs)
    np.testing.assert_allclose(qdd2, qdd, atol=1e-12)
    np.testing.assert_allclose(lam2, lam, atol=1e-12)
    diagonal = jnp.diag(jnp.diagonal(mass))
    qdd3, lam3 = solve_kkt(diagonal, force, rows, rhs, diagonal_mass=True)
    qdd4, lam4 = solve_kkt(diagonal, force, rows, rhs)
    np.testing.assert_allclose(qdd3, qdd4, atol=1e-12)
    np.testing.assert_allclose(lam3, lam4, atol=1e-12)
