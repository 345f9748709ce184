"""Bad input fails loudly with a message that names the problem."""

import jax
import jax.numpy as jnp
import pytest

import jaxlag as jl

TS = jnp.linspace(0.0, 1.0, 3)


def oscillator(q, qd):
    return 0.5 * jnp.sum(qd**2) - 0.5 * jnp.sum(q**2)


def test_non_scalar_lagrangian():
    with pytest.raises(ValueError, match="must return a scalar"):
        jl.simulate(jl.System(lambda q, qd: 0.5 * qd**2), [1.0, 2.0], [0.0, 0.0], TS)


def test_shapes_of_q_and_qd():
    with pytest.raises(ValueError, match="same shape"):
        jl.simulate(jl.System(oscillator), [1.0, 2.0], [0.0], TS)
    with pytest.raises(ValueError, match="1-D"):
        jl.simulate(jl.System(oscillator), [[1.0, 2.0]], [[0.0, 0.0]], TS)


def test_singular_mass_matrix():
    degenerate = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * jnp.sum(q**2))
    with pytest.raises(ValueError, match="singular or not positive definite"):
        jl.simulate(degenerate, [1.0, 2.0], [0.0, 0.0], TS)


def test_negative_definite_mass_matrix():
    with pytest.raises(ValueError, match="not positive definite"):
        jl.simulate(jl.System(lambda q, qd: -0.5 * jnp.sum(qd**2)), [1.0], [0.0], TS)


def test_non_finite_initial_state():
    with pytest.raises(ValueError, match="not finite"):
        jl.simulate(jl.System(oscillator), [jnp.nan], [0.0], TS)


def test_checks_still_fire_under_jit_and_vmap():
    run = jax.jit(lambda q0: jl.simulate(jl.System(oscillator), q0, jnp.zeros(1), TS).q)
    # Errors from compiled programs surface when the result is waited on (on GPU, after the
    # call has returned): block, as a user reading the result would.
    with pytest.raises(Exception, match="not finite"):
        jax.block_until_ready(run(jnp.array([jnp.inf])))
    degenerate = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * jnp.sum(q**2))
    batched = jax.vmap(lambda q0: jl.simulate(degenerate, q0, jnp.zeros(2), TS).q)
    with pytest.raises(Exception, match="singular or not positive definite"):
        jax.block_until_ready(batched(jnp.ones((3, 2))))


def test_time_grid_must_increase():
    with pytest.raises(ValueError, match="increasing"):
        jl.simulate(jl.System(oscillator), [1.0], [0.0], jnp.array([0.0, 1.0, 0.5]))


def test_missing_time_span():
    with pytest.raises(ValueError, match="ts"):
        jl.simulate(jl.System(oscillator), [1.0], [0.0])


def test_integer_initial_state_is_promoted():
    traj = jl.simulate(jl.System(oscillator), [1], [0], TS)
    assert jnp.issubdtype(traj.q.dtype, jnp.floating)


def test_host_and_compiled_initial_checks_agree():
    """Eager checks take M's eigenvalues and the constraint rows' singular values with NumPy on
    the host (no LAPACK in the check program: its first lowering costs ~0.1 s a process); the
    compiled check (under jit, vmap, simulate_batch) takes them in the program. Same flags."""
    import numpy as np

    from jaxlag import _checks as checks

    def pendulum(q, qd, args):
        return 0.5 * jnp.sum(qd**2) - args["g"] * q[1]

    cases = [
        (jl.System(oscillator), [1.0, 2.0], [0.0, 0.0]),  # all fine
        (jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * jnp.sum(q**2)), [1.0, 2.0], [0.0, 0.0]),
        (jl.System(pendulum, lambda q: jnp.array([jnp.sum(q**2) - 1.0])), [0.6, -0.8], [0.8, 0.6]),
        (jl.System(pendulum, lambda q: jnp.array([jnp.sum(q**2) - 1.0])), [0.7, -0.8], [0.0, 1.0]),
        (
            jl.System(pendulum, lambda q: jnp.array([jnp.sum(q**2) - 1.0, 2 * jnp.sum(q**2) - 2.0])),
            [0.6, -0.8],
            [0.8, 0.6],
        ),  # redundant rows
    ]
    args = {"g": 9.81}
    for system, q, qd in cases:
        q, qd = jnp.asarray(q), jnp.asarray(qd)
        values, host = checks._diagnostics_on_host(system, q, qd, 0.0, args, 1e-8)
        _, compiled = jax.device_get(checks._diagnostics(system, q, qd, 0.0, args, 1e-8))
        assert {k: bool(v) for k, v in host.items()} == {k: bool(v) for k, v in compiled.items()}
        np.testing.assert_allclose(values["eigenvalues"], np.linalg.eigvalsh(values["mass"]))
    assert any(bool(v) for v in host.values())  # the redundant rows are caught


# ----------------------------------------------------------------------------- the right cause
# Each message names what is actually wrong (the value, the position, the parameter) and the fix;
# inside jit/vmap the static message names the same cause.
import numpy as np  # noqa: E402

from jaxlag import systems  # noqa: E402

MODES = ("eager", "jit", "vmap")


def _run(mode, fn, x):
    if mode == "eager":
        return jax.block_until_ready(fn(x))
    if mode == "jit":
        return jax.block_until_ready(jax.jit(fn)(x))
    return jax.block_until_ready(jax.vmap(fn)(x[None]))


# Overdamped oscillator: q̈ = −q − c q̇ with c = 1e7, M = 1. The fast mode λ ≈ −c decays; an
# explicit solver is stable only for dt ≲ 3/c = 3e-7, below the 64-ulp time resolution of
# float32 on [0, 1] (64 · 1.19e-7 = 7.6e-6): the step size "collapses" although nothing is singular.
STIFF = jl.System(
    lambda q, qd: 0.5 * qd @ qd - 0.5 * q @ q, dissipation=lambda q, qd, args: 0.5 * args * qd @ qd
)
TS32 = jnp.linspace(0.0, 1.0, 3, dtype=jnp.float32)


@pytest.mark.parametrize("mode", MODES)
def test_float32_stiffness_is_not_called_a_singularity(mode):
    def run(c):
        return jl.simulate(
            STIFF, jnp.ones(1, jnp.float32), jnp.zeros(1, jnp.float32), TS32, args=c, throw=False
        )

    traj = _run(mode, run, jnp.float32(1e7))
    assert traj.q.dtype == jnp.float32 and int(np.ravel(traj.failure.code)[0]) == 5
    if mode == "eager":
        with pytest.raises(jl.SimulationError) as info:
            traj.raise_if_failed()
        text = str(info.value)
        assert "singularity here" not in text and "fast mode here, not a singularity" in text
        # λ of [[0, 1], [−1, −c]] is −c(1 + O(c⁻²)): printed to 3 digits.
        assert "λ = -1e+07 (stiff" in text and "mostly in q̇[0]" in text
        assert "3/|λ| = 3e-07" in text and "resolved on this interval is 7.6e-06" in text
        assert "float64" in text and "pass max_steps=4194304" in text
    else:
        with pytest.raises(Exception, match="stiffness that needs steps below the time resolution"):
            _run(
                mode,
                lambda c: (
                    jl.simulate(STIFF, jnp.ones(1, jnp.float32), jnp.zeros(1, jnp.float32), TS32, args=c).q
                ),
                jnp.float32(1e7),
            )


def test_singularity_is_still_a_singularity():
    """M = q² vanishes at t = 1/2 (q = √(1 − 2t)): ρ·dt ≈ 0.05 there, no fast mode."""
    singular = jl.System(lambda q, qd: 0.5 * q[0] ** 2 * qd[0] ** 2)
    with pytest.raises(jl.SimulationError, match="appears to reach a singularity"):
        jl.simulate(singular, jnp.ones(1), -jnp.ones(1), TS)


# Coulomb friction on a unit oscillator: q̈ = −q − ½ sign(q̇), from q = 1 at rest. The block slides
# left for half a period, its centre shifted to +½: it stops at q = 0, t = π, where the spring (0)
# is below the friction bound (½): it sticks, and sign(q̇) chatters at q̇ = 0 for ever.
COULOMB = jl.System(lambda q, qd: 0.5 * qd @ qd - 0.5 * q @ q, forces=lambda q, qd: -0.5 * jnp.sign(qd))
TS_STICK = jnp.linspace(0.0, 5.0, 3)


@pytest.mark.parametrize("mode", MODES)
def test_coulomb_chatter_is_a_discontinuity_not_max_steps(mode):
    def run(q0, throw=False):
        return jl.simulate(COULOMB, q0, jnp.zeros(1), TS_STICK, max_steps=4096, throw=throw)

    traj = _run(mode, run, jnp.ones(1))
    failure = jax.tree.map(lambda x: np.ravel(x)[0] if isinstance(x, jax.Array) else x, traj.failure)
    assert int(failure.code) == 2
    # Stuck where the closed form sticks: q = 0 from t = π on (the chatter creeps by dt per step).
    assert abs(float(failure.q)) < 1e-8 and np.pi - 1e-6 < float(failure.t) < np.pi + 1e-3
    if mode == "eager":
        with pytest.raises(jl.SimulationError) as info:
            run(jnp.ones(1), throw=True)
        text = str(info.value)
        assert "stuck at a discontinuity" in text and "Pass max_steps" not in text
        assert "q̈ jumps by 1 (q̈[0] from 0.5 to -0.5) where q̇[0] crosses 0" in text
        assert "No number of steps will finish it" in text and "tanh(v/ε)" in text
    else:
        with pytest.raises(Exception, match="stuck at a discontinuous force"):
            _run(mode, lambda q0: run(q0, throw=True).q, jnp.ones(1))


def test_regularized_friction_is_smooth():
    """tanh(q̇/ε) instead of sign: no discontinuity, the run completes (creeping at q ≈ 0)."""
    smooth = jl.System(
        lambda q, qd: 0.5 * qd @ qd - 0.5 * q @ q, forces=lambda q, qd: -0.5 * jnp.tanh(qd / 1e-2)
    )
    traj = jl.simulate(smooth, jnp.ones(1), jnp.zeros(1), TS_STICK)
    assert abs(float(traj.q[-1, 0])) < 0.05


# A constraint whose Jacobian is NaN on the manifold: |x| written as sqrt(x²), at x = 0.
KINK = jl.System(
    lambda q, qd: 0.5 * qd @ qd - 9.81 * q[1],
    holonomic=lambda q: jnp.array([jnp.sqrt(q[0] ** 2) + q[1] - 1.0]),
)


@pytest.mark.parametrize("mode", MODES)
def test_nan_constraint_jacobian_is_named(mode):
    def run(q0):
        return jl.simulate(KINK, q0, jnp.zeros(2), TS).q

    if mode == "eager":
        match = (
            r"constraint Jacobian is not finite at the initial state, although the constraints are: "
            r"J\[0, 0\] = ∂f_0/∂q_0 = nan \(holonomic\[0\], q\[0\]\)"
        )
        with pytest.raises(ValueError, match=match):
            run(jnp.array([0.0, 1.0]))
        with pytest.raises(ValueError, match=r"System.accelerations is not finite .*J\[0, 0\]"):
            KINK.accelerations(jnp.array([0.0, 1.0]), jnp.zeros(2))
    else:
        with pytest.raises(Exception, match=r"constraint Jacobian \(J = ∂f/∂q, or A = ∂g/∂q̇\) is not finite"):
            _run(mode, run, jnp.array([0.0, 1.0]))


@pytest.mark.parametrize("mode", ("eager", "jit"))
def test_forgotten_args_axes_names_the_leaf(mode):
    def L(q, qd, args):
        return 0.5 * qd @ qd - 0.5 * args["k"] * jnp.sum(q**2)

    system = jl.System(L)

    def run(k):
        return jl.simulate_batch(system, jnp.ones((3, 1)), jnp.zeros((3, 1)), TS, args={"k": k, "g": 1.0}).q

    match = r"returned shape \(3,\) because of args\['k'\] \(shape \(3,\)\).*args_axes=\{'k': 0\}"
    with pytest.raises(ValueError, match=match):
        (run if mode == "eager" else jax.jit(run))(jnp.array([1.0, 2.0, 3.0]))
    # Writing q @ q instead of jnp.sum(q**2) fails inside L first: the same leaf is named.
    system = jl.System(lambda q, qd, args: 0.5 * qd @ qd - 0.5 * args["k"] * q @ q)
    with pytest.raises(ValueError, match=r"Lagrangian failed \(TypeError.*args\['k'\].*args_axes=\{'k': 0\}"):
        (run if mode == "eager" else jax.jit(run))(jnp.array([1.0, 2.0, 3.0]))
    with pytest.raises(
        ValueError, match=r"Nothing to batch.*including args\['k'\] \(shape \(3,\)\).*args_axes=0"
    ):
        jl.simulate_batch(system, jnp.ones(1), jnp.zeros(1), TS, args={"k": jnp.ones(3)})
    # With the axis marked, member b has k = b + 1: q(t) = cos(√k t).
    traj = jl.simulate_batch(
        jl.System(L),
        jnp.ones((3, 1)),
        jnp.zeros((3, 1)),
        TS,
        args={"k": jnp.array([1.0, 2.0, 3.0]), "g": 1.0},
        args_axes={"k": 0, "g": None},
    )
    expected = np.cos(np.sqrt([1.0, 2.0, 3.0])[:, None] * np.asarray(TS)[None, :])
    np.testing.assert_allclose(traj.q[..., 0], expected, atol=1e-8)


# A pendulum in Cartesian coordinates: one constraint x² + y² = 1 in two coordinates.
ROD = jl.System(lambda q, qd: 0.5 * qd @ qd - 9.81 * q[1], holonomic=lambda q: jnp.array([q @ q - 1.0]))


@pytest.mark.parametrize("mode", MODES)
def test_too_many_fixed_coordinates_names_the_row(mode):
    def project(q0):
        return jl.consistent_initial_state(ROD, q0, jnp.zeros(2), fixed_q=(0, 1))[0]

    if mode == "eager":
        with pytest.raises(
            ValueError,
            match=r"fixed_q=\(0, 1\) holds more coordinates than the constraints allow: 0 free \(none\) "
            r"for 1 position constraints.*Left without a free coordinate: holonomic\[0\] \(it involves "
            r"only held coordinates q\[0\], q\[1\]\)\. Release one of q\[0\], q\[1\] from fixed_q",
        ):
            project(jnp.array([0.6, -0.7]))
        # Holding one is fine: y follows from x = 0.6 on the circle (the lower branch).
        q, _ = jl.consistent_initial_state(ROD, jnp.array([0.6, -0.7]), jnp.zeros(2), fixed_q=0)
        np.testing.assert_allclose(q, [0.6, -0.8], atol=1e-12)
    else:
        with pytest.raises(
            Exception, match="more coordinates are held in fixed_q than the constraints allow"
        ):
            _run(mode, project, jnp.array([0.6, -0.7]))


@pytest.mark.parametrize("mode", ("eager", "jit"))
def test_misspelt_parameter_of_a_ready_model(mode):
    call = (lambda f, *a: f(*a)) if mode == "eager" else (lambda f, *a: jax.jit(f)(*a))
    cart = systems.cart_pole()

    def run(value, key="forse", system=cart, extra=None):
        return jl.simulate(
            system, jnp.array([0.0, 0.1]), jnp.zeros(2), TS, args={key: value, **(extra or {})}
        ).q

    with pytest.raises(
        KeyError, match=r"unknown parameter\(s\) \['forse'\] \('forse' -> did you mean 'force'\?\)"
    ):
        call(run, 1.0)
    with pytest.raises(KeyError, match=r"\['lenght'\] \('lenght' -> did you mean 'l'\?\)"):
        call(lambda v: run(v, "lenght", systems.n_link_pendulum(2)), 1.0)
    # With a control, the keys it reads are allowed; the others are still refused.
    damped = systems.cart_pole(lambda q, qd, args: -args["k"] * qd[0])
    call(lambda v: run(v, "k", damped), 2.0)
    with pytest.raises(
        KeyError,
        match=r"\['mm'\] \('mm' -> did you mean 'm'\?\), not parameters of the model nor read by the control",
    ):
        call(lambda v: run(v, "k", damped, {"mm": 0.3}), 2.0)


def test_off_manifold_message_of_a_long_chain_is_a_summary():
    chain = systems.n_link_pendulum(100, "cartesian")
    angles = jnp.full(100, 0.3)
    q0 = jnp.cumsum(jnp.stack([jnp.sin(angles), -jnp.cos(angles)], -1), axis=0).reshape(-1)
    q0 = q0.at[75].add(1e-3)  # y of point 37: links 37 and 38 change length by ∓ cos(0.3)·1e-3
    with pytest.raises(ValueError) as info:
        jl.simulate(chain, q0, jnp.zeros(200), TS)
    text = str(info.value)
    assert (
        "f(q0): 2 of 100 entries beyond 1e-08" in text
        and "largest f[38] = 0.000955, f[37] = -0.000955" in text
    )
    assert "ḟ = J q̇0 + ∂f/∂t: all 100 within tolerance" in text and len(text) < 600
