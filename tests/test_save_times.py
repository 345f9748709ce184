"""`SaveTimes` (jaxlag._solver.save_times): saving at given times from inside the solver state
returns bit-for-bit what ``diffrax.SaveAt(ts=ts)`` returns, with no host callback in the program,
under jit, vmap, reverse and forward mode, with events and with ``t0 == t1``."""

import re

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlag._solver.save_times import SaveTimes, saved_values

_TERM = diffrax.ODETerm(lambda t, y, a: jnp.stack([y[1], -a * jnp.sin(y[0]) - 0.1 * y[1] * y[0]]))
_CONTROLLER = diffrax.PIDController(rtol=1e-9, atol=1e-9)
_TS = jnp.linspace(0.0, 7.0, 57)
_Y0 = jnp.array([1.2, 0.3])


def _diffrax(y0, a, ts, adjoint=diffrax.RecursiveCheckpointAdjoint(), event=None):
    solution = diffrax.diffeqsolve(
        _TERM, diffrax.Tsit5(), ts[0], ts[-1], None, y0, a,
        saveat=diffrax.SaveAt(ts=ts), stepsize_controller=_CONTROLLER, adjoint=adjoint,
        event=event, throw=False, max_steps=4096,
    )  # fmt: skip
    return solution.ys


def _ours(y0, a, ts, adjoint=diffrax.RecursiveCheckpointAdjoint(), event=None):
    solution = diffrax.diffeqsolve(
        _TERM, SaveTimes.for_adjoint(diffrax.Tsit5(), ts, adjoint), ts[0], ts[-1], None, y0, a,
        saveat=diffrax.SaveAt(t1=True, solver_state=True), stepsize_controller=_CONTROLLER,
        adjoint=adjoint, event=event, throw=False, max_steps=4096,
    )  # fmt: skip
    return saved_values(solution, ts, ts[0], ts[-1], y0, a)


def _callbacks(fn, *args):
    return len(re.findall(r"callback\[", str(jax.make_jaxpr(fn)(*args))))


def test_bit_for_bit_and_no_host_callbacks():
    expected, ours = jax.jit(_diffrax)(_Y0, 1.0, _TS), jax.jit(_ours)(_Y0, 1.0, _TS)
    np.testing.assert_array_equal(ours, expected)
    assert _callbacks(_diffrax, _Y0, 1.0, _TS) > 0  # what this module exists to avoid
    assert _callbacks(_ours, _Y0, 1.0, _TS) == 0


def test_vmap_over_states_and_times():
    y0s = _Y0[None] + jnp.linspace(-0.5, 0.5, 5)[:, None]
    tss = _TS[None] * jnp.linspace(0.5, 1.0, 5)[:, None]
    expected = jax.vmap(_diffrax, in_axes=(0, None, 0))(y0s, 1.0, tss)
    np.testing.assert_array_equal(jax.jit(jax.vmap(_ours, in_axes=(0, None, 0)))(y0s, 1.0, tss), expected)


@pytest.mark.parametrize("adjoint", [diffrax.RecursiveCheckpointAdjoint(), diffrax.DirectAdjoint()])
def test_reverse_mode(adjoint):
    def loss(solve, a):
        return jnp.sum(solve(_Y0, a, _TS, adjoint) ** 2)

    expected = jax.grad(lambda a: loss(_diffrax, a))(1.0)
    np.testing.assert_allclose(jax.jit(jax.grad(lambda a: loss(_ours, a)))(1.0), expected, rtol=1e-13)


def test_forward_mode():
    adjoint = diffrax.ForwardMode()
    _, expected = jax.jvp(lambda a: _diffrax(_Y0, a, _TS, adjoint), (1.0,), (1.0,))
    _, ours = jax.jit(lambda a: jax.jvp(lambda a: _ours(_Y0, a, _TS, adjoint), (a,), (1.0,)))(1.0)
    np.testing.assert_allclose(ours, expected, rtol=1e-13, atol=1e-15)


def test_saves_after_a_terminating_event_are_inf():
    # The pendulum crosses θ = 0 between saves: both return inf after the event time.
    event = diffrax.Event(lambda t, y, args, **kw: y[0], root_finder=None)
    expected, ours = _diffrax(_Y0, 1.0, _TS, event=event), _ours(_Y0, 1.0, _TS, event=event)
    reached = np.isfinite(np.asarray(expected[:, 0]))
    assert 0 < reached.sum() < len(_TS)
    np.testing.assert_array_equal(ours, expected)


def test_t0_equal_to_t1_saves_the_initial_state():
    ts = jnp.zeros(3)
    np.testing.assert_array_equal(_ours(_Y0, 1.0, ts), _diffrax(_Y0, 1.0, ts))


def test_dt0_of_the_wrong_sign_is_refused_on_the_host():
    import jaxlag as jl

    pendulum = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 + jnp.cos(q[0]))
    with pytest.raises(ValueError, match="dt0 must be finite, nonzero and have the sign of t1 - t0"):
        jl.simulate(pendulum, jnp.array([0.5]), jnp.zeros(1), jnp.linspace(0, 1, 5), dt0=-0.1)


def test_a_given_dt0_is_the_first_step():
    # dt0 reaches the controller through the guard (diffeqsolve gets dt0=None): constant steps of
    # dt0 take (t1 - t0)/dt0 steps, and a traced dt0 gives the same trajectory.
    import jaxlag as jl

    pendulum = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 + jnp.cos(q[0]))
    run = lambda dt0: jl.simulate(  # noqa: E731
        pendulum, jnp.array([0.5]), jnp.zeros(1), jnp.linspace(0, 1, 5), solver=jl.RK4(),
        stepsize_controller=diffrax.ConstantStepSize(), dt0=dt0,
    )  # fmt: skip
    eager = run(0.05)
    assert int(eager.stats["num_steps"]) == 20
    np.testing.assert_array_equal(jax.jit(lambda d: run(d).q)(0.05), eager.q)
