"""A failed run raises under jax.jit(jax.grad(...)) too, whatever output the loss reads.

Before: the compiled failure check sat on ``traj.q`` only and in the primal outputs only, so a
program that uses just the gradient (the primal outputs unused) dropped it as dead code and
returned the gradient of a truncated run silently (e.g. d(2nd bounce time)/dh with
``max_segments`` too small for the bounces). The check now also guards the residuals the
reverse pass reads.
"""

import jax
import jax.numpy as jnp
import pytest

import jaxlag as jl


def _ball():
    def lagrangian(q, qd):
        return 0.5 * qd[0] ** 2 - 9.81 * q[0]

    return jl.System(lagrangian, lambda q: q, unilateral=jl.Unilateral(0, restitution=0.8))


def _run(h, max_segments=2):
    return jl.simulate(
        _ball(),
        jnp.stack([h]),
        jnp.zeros(1),
        jnp.linspace(0.0, 3.0, 4),
        events=jl.Events(max_segments=max_segments),
    )


def test_max_segments_failure_raises_when_only_an_event_time_is_differentiated():
    def second_bounce(h):
        return _run(h).events.time[1]  # needs 3+ segments over [0, 3]: 2 are allowed

    # Under vmap the same check is batched (jit(vmap(grad)) raised too when this was fixed); one
    # compile of the gradient program suffices here.
    with pytest.raises(Exception, match="max_segments"):
        jax.block_until_ready(jax.jit(jax.grad(second_bounce))(1.0))


def test_max_steps_failure_raises_under_jit_grad_of_a_state():
    oscillator = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2)

    def final_position(x0):  # 30 s of oscillation cannot be done in 3 steps
        return jl.simulate(oscillator, jnp.stack([x0]), jnp.zeros(1), jnp.array([0.0, 30.0]), max_steps=3).q[
            -1, 0
        ]

    with pytest.raises(Exception, match="max_steps"):
        jax.block_until_ready(jax.jit(jax.grad(final_position))(1.0))


def test_max_steps_failure_raises_under_jit_grad_through_simulate_batch():
    oscillator = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2)

    def final_positions(x0):
        q0 = jnp.stack([x0, 2.0 * x0])[:, None]
        traj = jl.simulate_batch(oscillator, q0, jnp.zeros((2, 1)), jnp.array([0.0, 30.0]), max_steps=3)
        return traj.q[:, -1, 0].sum()

    with pytest.raises(Exception, match="max_steps"):
        jax.block_until_ready(jax.jit(jax.grad(final_positions))(1.0))
