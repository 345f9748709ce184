r"""The default adjoint, ``jl.ForwardSensitivities``: ``jax.grad`` by forward sensitivities
for few differentiated scalars, by diffrax's checkpointed reverse pass for many.

Every gradient is compared with diffrax's ``RecursiveCheckpointAdjoint`` on the same problem.
Both differentiate the same discrete solver exactly (same steps, same step-size decisions), so
they agree to rounding accumulated over the run: 1e-9 relative leaves three orders of
magnitude above what was measured (≤ 5e-13 in ``benchmarks/``).
"""

from __future__ import annotations

import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
from jaxlag._adjoint import call_with_forward_sensitivities

jax.config.update("jax_enable_x64", True)

TS = jnp.linspace(0.0, 2.0, 41)
FS = jl.ForwardSensitivities()
REVERSE = diffrax.RecursiveCheckpointAdjoint()


def double_pendulum(q, qd, args):
    l1, l2, g = args["l1"], args["l2"], args["g"]
    kinetic = 0.5 * (
        2 * l1**2 * qd[0] ** 2 + l2**2 * qd[1] ** 2 + 2 * l1 * l2 * qd[0] * qd[1] * jnp.cos(q[0] - q[1])
    )
    return kinetic + g * (2 * l1 * jnp.cos(q[0]) + l2 * jnp.cos(q[1]))


SYSTEM = jl.System(double_pendulum)
PARAMS = {"l1": jnp.asarray(1.0), "l2": jnp.asarray(0.8), "g": jnp.asarray(9.81)}
Q0, QD0 = jnp.array([1.0, 0.5]), jnp.array([0.0, -0.3])


def _close(a, b, rtol=1e-9):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=rtol, atol=1e-12)


@pytest.mark.parametrize("steps", ["adaptive", "constant"])
def test_grad_equals_default_adjoint(steps):
    kwargs = {} if steps == "adaptive" else dict(stepsize_controller=diffrax.ConstantStepSize(), dt0=1e-3)

    def loss(params, q0, adjoint):
        traj = jl.simulate(SYSTEM, q0, QD0, TS, args=params, adjoint=adjoint, **kwargs)
        return jnp.sum(traj.q**2) + jnp.sum(jnp.sin(traj.qd[-1])) + traj.energy[-1]

    expected = jax.grad(loss, argnums=(0, 1))(PARAMS, Q0, REVERSE)
    got = jax.grad(loss, argnums=(0, 1))(PARAMS, Q0, FS)
    _close(got, expected)
    # Only the parameters differentiated (the initial state fixed): fewer tangents, same answer.
    _close(jax.grad(loss)(PARAMS, Q0, FS), expected[0])
    value, grads = jax.jit(jax.value_and_grad(loss), static_argnums=2)(PARAMS, Q0, FS)
    np.testing.assert_allclose(value, loss(PARAMS, Q0, REVERSE), rtol=1e-12)
    _close(grads, expected[0])


def test_vmap_of_grad_and_vjp():
    def final(g, adjoint):
        params = dict(PARAMS, g=g)
        return jl.simulate(SYSTEM, Q0, QD0, TS, args=params, adjoint=adjoint).q[-1]

    gs = jnp.array([9.0, 9.81, 10.5])
    per_g = jax.vmap(jax.grad(lambda g: jnp.sum(final(g, FS) ** 2)))(gs)
    for i, g in enumerate(gs):
        np.testing.assert_allclose(
            per_g[i], jax.grad(lambda x: jnp.sum(final(x, REVERSE) ** 2))(g), rtol=1e-9
        )
    out, pullback = jax.vjp(lambda g: final(g, FS), gs[0])
    (cot,) = pullback(jnp.array([1.0, -2.0]))
    _, pullback_ref = jax.vjp(lambda g: final(g, REVERSE), gs[0])
    np.testing.assert_allclose(cot, pullback_ref(jnp.array([1.0, -2.0]))[0], rtol=1e-9)


def test_constrained_with_projection_and_release_event():
    # Particle released from a sphere: d t_release / d g = −t_release / (2g) (time scales as
    # sqrt(R/g) for a start at rest), checked against the closed form and the default adjoint.
    def lagrangian(q, qd, args):
        return 0.5 * jnp.sum(qd**2) - args * q[1]

    def sphere(q):
        return jnp.array([jnp.sqrt(q[0] ** 2 + q[1] ** 2) - 1.0])

    system = jl.System(lagrangian, sphere, unilateral=0)
    q0 = jnp.array([jnp.sin(0.2), jnp.cos(0.2)])

    def release_time(g, adjoint):
        traj = jl.simulate(system, q0, jnp.zeros(2), jnp.linspace(0.0, 2.0, 21), args=g, adjoint=adjoint)
        return traj.events.time[0]

    g = jnp.asarray(9.81)
    t_release = release_time(g, FS)
    d_fs = jax.grad(release_time)(g, FS)
    np.testing.assert_allclose(d_fs, -t_release / (2 * g), rtol=1e-7)
    np.testing.assert_allclose(d_fs, jax.grad(release_time)(g, REVERSE), rtol=1e-9)


def test_nothing_differentiated_and_forward_mode_pointer():
    traj = jl.simulate(SYSTEM, Q0, QD0, TS, args=PARAMS, adjoint=FS)
    np.testing.assert_allclose(
        traj.q, jl.simulate(SYSTEM, Q0, QD0, TS, args=PARAMS, adjoint=REVERSE).q, rtol=0, atol=0
    )
    # A gradient that does not reach any input of the simulation (k = 0 perturbed leaves).
    assert (
        float(
            jax.grad(lambda s: s * jnp.sum(jl.simulate(SYSTEM, Q0, QD0, TS, args=PARAMS, adjoint=FS).q))(2.0)
        )
        != 0.0
    )
    with pytest.raises(TypeError, match="custom_vjp"):
        jax.jacfwd(lambda g: jl.simulate(SYSTEM, Q0, QD0, TS, args=dict(PARAMS, g=g), adjoint=FS).q)(9.81)
    with pytest.raises(TypeError, match="adjoint"):
        jl.simulate(SYSTEM, Q0, QD0, TS, args=PARAMS, adjoint="forward")


def test_many_differentiated_scalars_fall_back_to_the_checkpointed_adjoint():
    weights = jnp.linspace(0.5, 1.5, 30)  # e.g. the weights of a learned kinetic term

    def lagrangian(q, qd, args):
        return 0.5 * jnp.mean(args**2) * jnp.sum(qd**2) - 0.5 * jnp.sum(q**2)

    def loss(w, adjoint):
        return jnp.sum(
            jl.simulate(jl.System(lagrangian), jnp.ones(2), jnp.zeros(2), TS[:3], args=w, adjoint=adjoint).q[
                -1
            ]
            ** 2
        )

    expected = jax.grad(loss)(weights, REVERSE)
    assert float(jnp.max(jnp.abs(expected))) > 1e-4
    _close(jax.grad(loss)(weights, FS), expected)  # 30 > max_tangents: reverse pass
    # Raising the limit gives forward sensitivities for all 30, with the same gradient.
    _close(jax.grad(loss)(weights, jl.ForwardSensitivities(max_tangents=64)), expected)
    # A byte limit below k × outputs also falls back.
    _close(jax.grad(loss)(weights, jl.ForwardSensitivities(max_tangents=64, max_bytes=1)), expected)


def test_default_adjoint_is_forward_sensitivities(monkeypatch):
    module = sys.modules["jaxlag._simulate"]
    calls = []

    def spy(run, inputs, choice, *rest):
        calls.append(choice)
        return call_with_forward_sensitivities(run, inputs, choice, *rest)

    monkeypatch.setattr(module, "call_with_forward_sensitivities", spy)

    def loss(g, adjoint=None):
        kwargs = {} if adjoint is None else {"adjoint": adjoint}
        return jnp.sum(jl.simulate(SYSTEM, Q0, QD0, TS, args=dict(PARAMS, g=g), **kwargs).q ** 2)

    np.testing.assert_allclose(jax.grad(loss)(9.81), jax.grad(loss)(9.81, REVERSE), rtol=1e-9)
    assert len(calls) == 1 and calls[0] == jl.ForwardSensitivities()
