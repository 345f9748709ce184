r"""``jax.grad`` through ``simulate`` by the one-loop tangent solve (``jaxlag.tangent_solve``).

The state and its k forward sensitivities are integrated in one diffrax loop (the variational
equations stepped by the same solver, the projection pushed forward; diffrax does not
differentiate its step-size choice either). Every gradient is
compared with diffrax's ``RecursiveCheckpointAdjoint`` on the same problem: both differentiate
the same discrete solver with the same steps, so they agree to rounding accumulated over the
run (measured ≤ 5e-16 relative on the README example); 1e-9 relative as in
``test_sensitivities``. Each test also checks that the tangent solve was the path taken.
"""

from __future__ import annotations

import sys

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
from jaxlag._solver.forwarding import ForwardingSolver

jax.config.update("jax_enable_x64", True)

REVERSE = diffrax.RecursiveCheckpointAdjoint()
SIMULATE = sys.modules["jaxlag._simulate"]


@pytest.fixture
def tangent_solves(monkeypatch):
    """Calls of the tangent solve (``_Run.push_along``; empty: the general paths were taken)."""
    calls = []
    original = SIMULATE._Run.push_along

    def spy(self, *args):
        calls.append(1)
        return original(self, *args)

    monkeypatch.setattr(SIMULATE._Run, "push_along", spy)
    return calls


def _close(a, b, rtol=1e-9):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=rtol, atol=1e-12)


def sphere_lagrangian(q, qd, args):
    r, th = q
    rd, thd = qd
    return 0.5 * args["m"] * (rd**2 + r**2 * thd**2) - args["m"] * args["g"] * r * jnp.cos(th)


SPHERE = jl.System(sphere_lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]))
SPHERE_ARGS = {"m": 1.0, "g": 9.81, "R": 2.0}
TS = jnp.linspace(0.0, 1.0, 11)


def test_constrained_projection_parameters_and_initial_state(tangent_solves):
    """Parameters in L and in the constraint, and the initial velocity: the projection after
    every step and at the save times is differentiated with the step."""

    def loss(args, qd0, adjoint=None):
        traj = jl.simulate(SPHERE, jnp.array([2.0, 0.1]), qd0, TS, args=args, adjoint=adjoint)
        return jnp.sum(traj.q[:, 1] ** 2) + jnp.sum(traj.qd[-1] ** 2) + traj.multipliers[-1, 0]

    qd0 = jnp.array([0.0, 0.3])
    got = jax.grad(loss, argnums=(0, 1))(SPHERE_ARGS, qd0)
    assert tangent_solves
    _close(got, jax.grad(loss, argnums=(0, 1))(SPHERE_ARGS, qd0, REVERSE))
    # Under jit, and with one differentiated scalar (k = 1).
    _close(jax.jit(jax.grad(loss))(SPHERE_ARGS, qd0), got[0])
    one = jax.grad(lambda g: loss(dict(SPHERE_ARGS, g=g), qd0))(9.81)
    np.testing.assert_allclose(one, got[0]["g"], rtol=1e-9)


def test_constant_mass_depending_on_parameters(tangent_solves):
    """A Cartesian particle on a circle: M = m·I is constant and inverted once per solve, from
    ``args`` (the tangent of that inverse enters every step through the equations' term)."""

    def lagrangian(q, qd, args):
        return 0.5 * args["m"] * jnp.sum(qd**2) - args["m"] * args["g"] * q[1] + 0.5 * args["k"] * q[0] ** 2

    system = jl.System(lagrangian, holonomic=lambda q: jnp.array([jnp.sum(q**2) - 1.0]))
    q0, qd0 = jnp.array([jnp.sin(0.4), -jnp.cos(0.4)]), jnp.zeros(2)

    def loss(args, adjoint=None):
        traj = jl.simulate(system, q0, qd0, TS, args=args, adjoint=adjoint)
        return jnp.sum(traj.q[:, 0] ** 3) + jnp.sum(traj.constraint_forces[-1])

    args = {"m": 1.3, "g": 9.81, "k": 0.5}
    got = jax.grad(loss)(args)
    assert tangent_solves
    _close(got, jax.grad(loss)(args, REVERSE))
    assert abs(float(got["m"])) > 1e-6  # the mass does matter here (the spring term)


@pytest.mark.parametrize("solver", [diffrax.Euler(), jl.RK4()])
def test_constant_steps_and_baumgarte(solver, tangent_solves):
    def lagrangian(q, qd, args):
        return 0.5 * jnp.sum(qd**2) - args["g"] * q[1]

    system = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([jnp.sum(q**2) - args["l"] ** 2]))
    q0, qd0 = jnp.array([0.6, -0.8]), jnp.array([0.8, 0.6])

    def loss(args, adjoint=None):
        traj = jl.simulate(
            system,
            q0,
            qd0,
            TS,
            args=args,
            adjoint=adjoint,
            solver=solver,
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=1e-3,
            baumgarte=jl.Baumgarte(alpha=5.0, beta=6.0),
            projection=None,
        )
        return jnp.sum(traj.q**2 * jnp.arange(1.0, 3.0)[None, :])

    args = {"g": 9.81, "l": 1.0}
    got = jax.grad(loss)(args)
    assert tangent_solves
    _close(got, jax.grad(loss)(args, REVERSE))


def test_other_inputs_take_the_general_path(tangent_solves):
    """Differentiated save times, a closure over a traced value of the caller (with traced
    inputs, so that the probe of the user's functions decides), or a wrapped solver (which may
    transform the state nonlinearly): the general paths, same answers."""

    def by_times(ts, adjoint=None):
        return jnp.sum(
            jl.simulate(SPHERE, jnp.array([2.0, 0.1]), jnp.zeros(2), ts, args=SPHERE_ARGS, adjoint=adjoint).q[
                :, 1
            ]
            ** 2
        )

    got = jax.grad(by_times)(TS)
    assert not tangent_solves
    _close(got, jax.grad(by_times)(TS, REVERSE))

    def by_closure(g, theta0, adjoint=None):
        system = jl.System(
            lambda q, qd: sphere_lagrangian(q, qd, dict(SPHERE_ARGS, g=g)),
            holonomic=lambda q: jnp.array([q[0] - 2.0]),
        )
        traj = jl.simulate(system, jnp.stack([2.0, theta0]), jnp.zeros(2), TS, adjoint=adjoint)
        return jnp.sum(traj.q[:, 1] ** 2)

    got = jax.grad(by_closure, argnums=(0, 1))(9.81, 0.1)
    assert not tangent_solves
    assert abs(float(got[0])) > 1e-3  # the captured g is differentiated, not dropped
    _close(got, jax.grad(by_closure, argnums=(0, 1))(9.81, 0.1, REVERSE))


def test_vmap_of_grad(tangent_solves):
    def loss(g):
        return jnp.sum(
            jl.simulate(SPHERE, jnp.array([2.0, 0.1]), jnp.zeros(2), TS, args=dict(SPHERE_ARGS, g=g)).q[:, 1]
            ** 2
        )

    gs = jnp.array([9.0, 9.81, 10.5])
    batched = jax.vmap(jax.grad(loss))(gs)
    assert tangent_solves
    for i, g in enumerate(gs):
        np.testing.assert_allclose(batched[i], jax.grad(loss)(g), rtol=1e-12)


class _Wrapped(ForwardingSolver, diffrax.AbstractWrappedSolver):
    """A user's solver wrapper (here a transparent one)."""

    solver: diffrax.AbstractSolver


@pytest.mark.parametrize("system", ["constrained", "unconstrained"])
def test_wrapped_solver_takes_the_general_path(system, tangent_solves):
    simulated = SPHERE if system == "constrained" else jl.System(sphere_lagrangian)

    def loss(args, adjoint=None):
        traj = jl.simulate(
            simulated,
            jnp.array([2.0, 0.1]),
            jnp.zeros(2),
            TS,
            args=args,
            adjoint=adjoint,
            solver=_Wrapped(diffrax.Tsit5()),
        )
        return jnp.sum(traj.q[:, 1] ** 2)

    got = jax.grad(loss)(SPHERE_ARGS)
    assert not tangent_solves
    _close(got, jax.grad(loss)(SPHERE_ARGS, REVERSE))
