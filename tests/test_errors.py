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
