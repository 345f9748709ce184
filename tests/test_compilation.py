"""Compilation: jaxlag's XLA options, and no recompilation where only values change.

Counts compilations with ``jax.monitoring`` (no timings: speed is measured by
``benchmarks/bench_first_result.py``).
"""

from __future__ import annotations

import contextlib
import threading

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import jaxlag as jl
from jaxlag import _compile as compilation
from jaxlag._solver.forwarding import ForwardingSolver

jax.config.update("jax_enable_x64", True)

_COMPILES = [0]


def _count(event, duration, **kwargs):
    if event == "/jax/core/compile/backend_compile_duration":
        _COMPILES[0] += 1


jax.monitoring.register_event_duration_secs_listener(_count)


@contextlib.contextmanager
def compilations():
    """Yields a list that holds, after the block, the number of XLA compilations inside it."""
    box, start = [], _COMPILES[0]
    yield box
    box.append(_COMPILES[0] - start)


def _sphere_lagrangian(q, qd, args):
    r, th = q
    rd, thd = qd
    return 0.5 * args["m"] * (rd**2 + r**2 * thd**2) - args["m"] * args["g"] * r * jnp.cos(th)


SPHERE = jl.System(_sphere_lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]))
PENDULUM = jl.System(
    lambda q, qd, args: 0.5 * args["l"] ** 2 * qd[0] ** 2 + args["g"] * args["l"] * jnp.cos(q[0])
)


def test_compiler_options(monkeypatch):
    expected = {"xla_cpu_use_fusion_emitters": False} if jax.default_backend() == "cpu" else {}
    monkeypatch.setattr(compilation.os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    assert jl.compiler_options() == expected
    assert jl.compiler_options("gpu") == {}
    # A process that may run on one core only: XLA's code generation is not split for threads.
    monkeypatch.setattr(compilation.os, "sched_getaffinity", lambda pid: {3}, raising=False)
    assert jl.compiler_options("cpu") == {
        "xla_cpu_use_fusion_emitters": False,
        "xla_cpu_parallel_codegen_split_count": 1,
    }
    monkeypatch.setenv("JAXLAG_COMPILER_OPTIONS", "0")
    assert jl.compiler_options("cpu") == {}


def test_user_jit_vmap_and_grad_with_and_without_options():
    """jaxlag's jitted functions traced inside a user's jit compile with the user's options
    (JAX allows options only on top-level programs): with or without them, same numbers."""
    ts = jnp.linspace(0.0, 1.0, 11)
    args = {"m": 1.0, "g": 9.81, "R": 2.0}

    def final_angle(q0, a):
        return jl.simulate(SPHERE, q0, jnp.zeros(2), ts, args=a).q[-1, 1]

    q0 = jnp.array([2.0, 0.1])
    eager = final_angle(q0, args)
    plain = jax.jit(final_angle)(q0, args)
    tuned = jax.jit(final_angle, compiler_options=jl.compiler_options())(q0, args)
    np.testing.assert_allclose([plain, tuned], [eager, eager], rtol=1e-12)
    batch = jax.jit(jax.vmap(final_angle, in_axes=(0, None)))(jnp.stack([q0, q0]), args)
    np.testing.assert_allclose(batch, [eager, eager], rtol=1e-12)
    grad_eager = jax.grad(final_angle, argnums=1)(q0, args)
    grad_jit = jax.jit(jax.grad(final_angle, argnums=1))(q0, args)
    for key in args:
        np.testing.assert_allclose(grad_jit[key], grad_eager[key], rtol=1e-10)


def test_new_values_do_not_recompile():
    """A second simulate and a second jax.grad with new values of q0, args and ts (same shapes)
    compile nothing, including the forward-sensitivity program of the default adjoint."""

    def run(theta, g, t_end):
        ts = jnp.linspace(0.0, t_end, 11)
        traj = jl.simulate(
            SPHERE, jnp.array([2.0, theta]), jnp.zeros(2), ts, args={"m": 1.0, "g": g, "R": 2.0}
        )
        loss = jax.grad(
            lambda a: jnp.sum(
                jl.simulate(SPHERE, jnp.array([2.0, theta]), jnp.zeros(2), ts, args=a).q[:, 1] ** 2
            )
        )
        return traj.q, loss({"m": 1.0, "g": g, "R": 2.0})

    jax.block_until_ready(run(0.1, 9.81, 1.0))
    with compilations() as count:
        q, grads = jax.block_until_ready(run(0.2, 9.7, 0.9))
    assert count == [0]
    assert np.all(np.isfinite(q)) and np.isfinite(grads["g"])


def test_fit_twice_compiles_once_and_stops_at_the_noise_floor():
    """A second fit (new data, new starting values) compiles nothing; the fit stops within a
    few steps once the trial steps are below its tolerance (rejections at the noise floor do
    not shrink the step down to zero)."""
    bob = lambda q, qd, args: args["l"] * jnp.array([jnp.sin(q[0]), -jnp.cos(q[0])])  # noqa: E731
    ts = jnp.linspace(0.0, 2.0, 41)

    def fit(truth, guess, seed):
        traj = jl.simulate(PENDULUM, jnp.array([0.5]), jnp.zeros(1), ts, args=truth)
        data = jax.vmap(lambda q, qd: bob(q, qd, truth))(traj.q, traj.qd)
        data = data + 1e-3 * np.random.default_rng(seed).standard_normal(data.shape)
        return jl.fit(
            PENDULUM,
            guess,
            jl.Experiment(ts, data, jnp.array([0.5]), jnp.zeros(1)),
            observe=bob,
            transforms={"g": jl.Positive(), "l": jl.Positive()},
        )

    first = fit({"g": 9.81, "l": 0.8}, {"g": 11.0, "l": 0.6}, 0)
    with compilations() as count:
        second = fit({"g": 9.7, "l": 0.9}, {"g": 8.0, "l": 1.1}, 1)
    assert count == [0]
    for result, truth in ((first, {"g": 9.81, "l": 0.8}), (second, {"g": 9.7, "l": 0.9})):
        assert result.converged and result.num_steps <= 12
        for key, value in truth.items():  # within 5 standard errors of the truth
            assert abs(float(result.params[key]) - value) < 5 * float(result.standard_errors[key])


def test_fit_with_equal_option_objects_compiles_once():
    """The option objects of a fit (optimizer, shooting, simulation options) are part of the
    cache key by value: a second fit with new, equal objects (new data, new starting values)
    compiles nothing."""
    bob = lambda q, qd, args: args["l"] * jnp.array([jnp.sin(q[0]), -jnp.cos(q[0])])  # noqa: E731
    ts = jnp.linspace(0.0, 2.0, 41)

    def fit(truth, guess, seed):
        traj = jl.simulate(PENDULUM, jnp.array([0.5]), jnp.zeros(1), ts, args=truth)
        data = jax.vmap(lambda q, qd: bob(q, qd, truth))(traj.q, traj.qd)
        data = data + 1e-3 * np.random.default_rng(seed).standard_normal(data.shape)
        return jl.fit(
            PENDULUM,
            guess,
            jl.Experiment(ts, data, jnp.array([0.5]), jnp.zeros(1)),
            observe=bob,
            transforms={"g": jl.Positive(), "l": jl.Positive()},
            optimizer=optx.GaussNewton(rtol=1e-8, atol=1e-8),
            shooting=jl.Shooting(segments=2, continuity_weight=5.0),
            solver=diffrax.Dopri5(),
            stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9),
            max_solver_steps=4096,
        )

    first = fit({"g": 9.81, "l": 0.8}, {"g": 11.0, "l": 0.6}, 0)
    with compilations() as count:
        second = fit({"g": 9.7, "l": 0.9}, {"g": 8.0, "l": 1.1}, 1)
    assert count == [0]
    for result, truth in ((first, {"g": 9.81, "l": 0.8}), (second, {"g": 9.7, "l": 0.9})):
        assert result.converged
        for key, value in truth.items():  # within 5 standard errors of the truth
            assert abs(float(result.params[key]) - value) < 5 * float(result.standard_errors[key])


@pytest.mark.parametrize("mode", ["eager", "jit"])
def test_failure_inside_grad_is_raised(mode):
    """The forward-sensitivity rule raises run-time failures: with the numbers host-side when
    eager, with the static message of the cause from the program under jit."""

    def loss(g):
        return jnp.sum(
            jl.simulate(
                PENDULUM,
                jnp.array([0.5]),
                jnp.zeros(1),
                jnp.linspace(0.0, 50.0, 3),
                args={"g": g, "l": 1.0},
                max_steps=16,
            ).q
            ** 2
        )

    grad = jax.grad(loss) if mode == "eager" else jax.jit(jax.grad(loss))
    expected = "max_steps = 16" if mode == "eager" else "max_steps was reached before the end time"
    with pytest.raises(Exception, match=expected):
        jax.block_until_ready(grad(9.81))


def test_options_unknown_to_this_xla_fall_back_to_its_defaults(monkeypatch):

    monkeypatch.setattr(compilation, "CPU_COMPILER_OPTIONS", {"xla_no_such_option_here": True})
    compilation._cpu_options_supported.cache_clear()
    try:
        assert compilation.compiler_options("cpu") == {}
    finally:
        compilation._cpu_options_supported.cache_clear()


@pytest.mark.parametrize("helper", ["inline", "jitted"])
def test_a_check_inside_the_equations_of_motion_still_raises(helper):
    """An ``eqx.error_if`` in a user's Lagrangian raises, also inside a user's ``jax.jit``
    helper, whose trace JAX caches."""

    def in_range(q):
        return eqx.error_if(q, q[0] > 0.4, "the angle left the model's range")

    check = jax.jit(in_range) if helper == "jitted" else in_range

    def lagrangian(q, qd, args):
        q = check(q)
        return 0.5 * qd[0] ** 2 + args["g"] * jnp.cos(q[0])

    system = jl.System(lagrangian)
    with pytest.raises(Exception, match="the angle left the model's range"):
        jax.block_until_ready(
            jl.simulate(
                system, jnp.array([0.3]), jnp.array([1.0]), jnp.linspace(0.0, 1.0, 5), args={"g": 9.81}
            ).q
        )


def test_simulations_traced_in_parallel_threads():
    """Simulations traced from several threads at once: every result equals the one traced
    alone."""
    system = jl.System(
        lambda q, qd, args: 0.5 * (qd @ qd) - args["g"] * q[1],
        holonomic=lambda q, args: jnp.array([q @ q - 1.0]),
    )
    q0 = jnp.array([jnp.sin(0.4), -jnp.cos(0.4)])
    sizes = (4, 5, 6, 7)  # one new trace per thread

    def run(size):
        return jl.simulate(system, q0, jnp.zeros(2), jnp.linspace(0.0, 0.3, size), args={"g": 9.81}).q[-1]

    results = {}
    threads = [threading.Thread(target=lambda s=s: results.__setitem__(s, run(s))) for s in sizes]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for size in sizes:
        np.testing.assert_allclose(results[size], run(size), rtol=0, atol=1e-13)


class _CountingSolver(ForwardingSolver, diffrax.AbstractWrappedSolver):
    """Tsit5 that counts the Python executions (traces) of its step."""

    solver: diffrax.AbstractSolver = diffrax.Tsit5()
    calls: list = eqx.field(static=True, default_factory=list)

    def __hash__(self):
        return id(self.calls)

    def __eq__(self, other):
        return isinstance(other, _CountingSolver) and other.calls is self.calls

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        self.calls.append(1)
        return self.solver.step(terms, t0, t1, y0, args, solver_state, made_jump)


@pytest.mark.parametrize("constrained", [False, True])
def test_solver_step_traced_once_per_solve(constrained):
    """diffrax traces its loop body three times; jaxlag's solver step (with the equations of
    motion and the projection in it) is traced once for simulate and once for the tangent solve
    of jax.grad (jaxlag._solver.step_once)."""
    holonomic = (lambda q, args: jnp.array([q[0] - args["R"]])) if constrained else None
    system = jl.System(lambda q, qd, args: 0.5 * jnp.sum(qd**2) - args["g"] * q[1], holonomic)
    args = {"g": 9.81, "R": 1.0}
    solver = _CountingSolver()
    traj = jl.simulate(
        system,
        jnp.array([1.0, 0.0]),
        jnp.array([0.0, 0.5]),
        jnp.linspace(0.0, 1.0, 5),
        args=args,
        solver=solver,
    )
    assert len(solver.calls) == 1
    # The same physics as without the wrapper: y = 0.5 t − g t²/2.
    np.testing.assert_allclose(traj.q[:, 1], 0.5 * traj.t - 0.5 * 9.81 * traj.t**2, atol=1e-10)
    solver.calls.clear()
    jax.grad(
        lambda a: jl.simulate(
            system,
            jnp.array([1.0, 0.0]),
            jnp.array([0.0, 0.5]),
            jnp.linspace(0.0, 1.0, 5),
            args=a,
            solver=solver,
        ).q[-1, 1]
    )(args)
    # A wrapped solver takes the general path (vmap of jvp of the traced solve), whose step is
    # the one simulate traced above (same solver, same shapes): served from the cache.
    assert len(solver.calls) <= 1


def test_equations_of_motion_traced_once_and_compiled_once():
    """``jl.EquationsOfMotion`` is jitted: the first call traces the Lagrangian, later calls at
    other times and parameter values (Python floats: not static) and other traces with the same
    shapes reuse that trace (diffrax's term check, its first step size and the solver step share
    it), and an eager call compiles one program. Closed form on the sphere r = R: r̈ = 0, θ̈ = (g/R) sin θ."""
    calls = []

    def lagrangian(q, qd, args):
        calls.append(1)
        return _sphere_lagrangian(q, qd, args)

    system = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]))
    field = jl.EquationsOfMotion(system)
    args = {"m": 1.0, "g": 9.81, "R": 2.0}
    y = (jnp.array([2.0, 0.3]), jnp.zeros(2))
    field(0.0, y, args)
    traced = len(calls)
    with compilations() as count:
        outs = [field(t, y, {**args, "g": g}) for t, g in ((0.1, 9.81), (0.2, 9.7), (0.3, 1.62))]
    assert count == [0] and len(calls) == traced  # new times and parameter values: no new program
    for (qd, qdd), g in zip(outs, (9.81, 9.7, 1.62), strict=True):
        np.testing.assert_allclose(qdd, [0.0, g / 2.0 * np.sin(0.3)], rtol=0, atol=1e-12)
    jax.make_jaxpr(lambda y: field(jnp.asarray(0.5), y, args))(y)
    assert len(calls) == traced
    thetas = jnp.linspace(-1.0, 1.0, 5)
    batched = jax.vmap(lambda th: field(0.0, (jnp.array([2.0, th]), jnp.zeros(2)), args)[1][1])(thetas)
    np.testing.assert_allclose(batched, 9.81 / 2.0 * np.sin(thetas), rtol=0, atol=1e-12)
    slope = jax.jit(jax.grad(lambda th: field(0.0, (jnp.array([2.0, th]), jnp.zeros(2)), args)[1][1]))(0.3)
    np.testing.assert_allclose(slope, 9.81 / 2.0 * np.cos(0.3), rtol=0, atol=1e-12)


def test_projection_traced_once_and_transformed():
    """``jl.Projection`` is jitted: the step's projection, the projection of the saved states
    (a ``vmap``) and the forward sensitivities' (a ``jvp``) transform one trace of it, so the
    user's constraint is not traced again for other times, under ``vmap`` or ``jax.jvp``. The
    projection lands on the sphere r = R with the radial velocity removed."""
    calls = []

    def on_sphere(q, args):
        calls.append(1)
        return jnp.array([q[0] - args["R"]])

    system = jl.System(_sphere_lagrangian, holonomic=on_sphere)
    args = {"m": 1.0, "g": 9.81, "R": 2.0}
    project = jl.Projection()
    q, qd = jnp.array([2.01, 0.3]), jnp.array([0.1, 0.5])
    q1, qd1 = project(system, q, qd, 0.0, args)
    traced = len(calls)
    project(system, q, qd, 0.7, args)
    at_zero = lambda x: project(system, x, qd, jnp.asarray(0.0), args)  # noqa: E731
    qs, _ = jax.vmap(at_zero)(jnp.stack([q, q + 0.001]))
    _, (dq, _) = jax.jvp(at_zero, (q,), (jnp.array([1.0, 0.0]),))
    assert len(calls) == traced
    np.testing.assert_allclose(q1, [2.0, 0.3], rtol=0, atol=1e-14)
    np.testing.assert_allclose(qd1, [0.0, 0.5], rtol=0, atol=1e-14)
    np.testing.assert_allclose(qs[:, 0], 2.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(dq, [0.0, 0.0], rtol=0, atol=1e-12)  # r is held at R


def test_eager_gradient_contracts_on_the_host():
    """An eager ``jax.grad`` through ``simulate`` compiles no program for ``θ̄ = Sᵀȳ`` (the
    sensitivities are contracted in NumPy) and equals the same gradient under ``jax.jit``."""
    names = []

    def listen(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            names.append(kwargs.get("fun_name"))

    ts = jnp.linspace(0.0, 1.0, 13)

    def loss(a):
        return jnp.sum(jl.simulate(PENDULUM, jnp.array([0.5]), jnp.zeros(1), ts, args=a).q ** 2)

    args = {"g": 9.81, "l": 0.8}
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        eager = jax.grad(loss)(args)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert isinstance(eager["g"], jax.Array) and eager["g"].dtype == jnp.float64
    assert not [n for n in names if n and "_contract" in n]
    compiled = jax.jit(jax.grad(loss))(args)
    for key in args:
        np.testing.assert_allclose(eager[key], compiled[key], rtol=1e-12)


def _program_names(fn):
    """``(fn(), names of the programs XLA compiled while it ran)``."""
    names = []

    def listen(event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            names.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        out = jax.block_until_ready(fn())
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return out, names


def _pendulum_lagrangian(q, qd):  # l = 1, g = 9.81: θ̈ = −9.81 sin θ
    return 0.5 * qd[0] ** 2 + 9.81 * jnp.cos(q[0])


def test_learned_accelerations_compile_once():
    """``jll.accelerations`` is one program per model and shapes, eagerly and under an eager
    ``jax.vmap`` (before: one program per operation, 99–163 of them for a DeLaN): new states
    and new weights compile nothing, and ``state_data`` is one program. Against θ̈ = −g sin θ."""
    from jaxlag import learned as jll

    thetas = jnp.linspace(-1.0, 1.0, 7)[:, None]
    at_rest = jnp.zeros(1)
    batched = lambda model, q: jax.vmap(lambda a: jll.accelerations(model, a, at_rest))(q)  # noqa: E731
    qdd, names = _program_names(lambda: batched(_pendulum_lagrangian, thetas))
    assert len(names) <= 2, names  # the solve, and at most the time 0.0 made an array
    np.testing.assert_allclose(qdd[:, 0], -9.81 * np.sin(thetas[:, 0]), rtol=0, atol=1e-12)
    shifted = thetas + 0.1
    with compilations() as count:
        again = batched(_pendulum_lagrangian, shifted)
    assert count == [0]
    np.testing.assert_allclose(again[:, 0], -9.81 * np.sin(shifted[:, 0]), rtol=0, atol=1e-12)

    model = jll.DeLaN(1, 8, 2, key=jax.random.PRNGKey(0))
    _, names = _program_names(lambda: batched(model, thetas))
    assert len(names) <= 2, names
    other = jll.DeLaN(1, 8, 2, key=jax.random.PRNGKey(1))  # same structure, new weights
    with compilations() as count:
        new = batched(other, thetas)
    assert count == [0]
    reference = eqx.filter_jit(batched)(other, thetas)
    np.testing.assert_allclose(new, reference, rtol=1e-12, atol=1e-12)

    ts = jnp.broadcast_to(jnp.linspace(0.0, 1.0, 5), (3, 5))
    data = jll.TrajectoryData(ts, jnp.broadcast_to(thetas[:3, None], (3, 5, 1)), jnp.zeros((3, 5, 1)))
    states, names = _program_names(lambda: jll.state_data(_pendulum_lagrangian, data))
    assert len(names) <= 2, names
    np.testing.assert_allclose(states.qdd[:, 0], -9.81 * np.sin(states.q[:, 0]), rtol=0, atol=1e-12)


def test_learned_losses_and_step_compile_once():
    """A built-in loss and ``jll.train_step`` called eagerly are one program each (before: 117
    and 232 for a small DeLaN), reused for new weights, and equal to the same calls under the
    user's ``eqx.filter_jit``. The loss of the true pendulum on its own accelerations is 0."""
    import optax

    from jaxlag import learned as jll

    q = jnp.linspace(-1.0, 1.0, 16)[:, None]
    qd = jnp.linspace(0.5, -0.5, 16)[:, None]
    states = jll.StateData(q, qd, -9.81 * jnp.sin(q))
    loss = jll.AccelerationLoss()
    exact, names = _program_names(lambda: loss(_pendulum_lagrangian, states).value)
    assert len(names) == 1, names
    assert float(exact) < 1e-24

    model = jll.DeLaN(1, 8, 2, key=jax.random.PRNGKey(0))
    value, names = _program_names(lambda: loss(model, states).value)
    assert len(names) == 1, names
    np.testing.assert_allclose(value, eqx.filter_jit(lambda m: loss(m, states).value)(model), rtol=1e-12)

    optimizer = optax.adam(1e-3)
    with jax.numpy_dtype_promotion("standard"):  # optax mixes int32 step counts with floats
        opt_state = eqx.filter_jit(optimizer.init)(eqx.filter(model, eqx.is_inexact_array))
        step = lambda m: jll.train_step(m, opt_state, states, loss, optimizer)  # noqa: E731
        (stepped, _, before), names = _program_names(lambda: step(model))
        assert len(names) == 1, names
        with compilations() as count:
            jax.block_until_ready(step(stepped))
        by_user = eqx.filter_jit(jll.train_step)(model, opt_state, states, loss, optimizer)[0]
    assert count == [0]
    np.testing.assert_allclose(before.value, value, rtol=1e-12)
    weights = lambda m: jax.tree.leaves(eqx.filter(m, eqx.is_array))  # noqa: E731
    for a, b in zip(weights(stepped), weights(by_user)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


def test_learned_data_helpers_compile_once():
    """``split`` and ``segments`` are one program each (before: 24 and 11 single operations),
    with the rows and samples of the NumPy reference; ``train`` stacks its per-step scalars on
    the host (no ``jit(stack)`` program per step count)."""
    from jaxlag import learned as jll

    ts = jnp.broadcast_to(jnp.linspace(0.0, 1.0, 9), (4, 9))
    q = jnp.arange(36.0).reshape(4, 9, 1)
    data = jll.TrajectoryData(ts, q, -q)
    cut, names = _program_names(lambda: jll.segments(data, 3))
    assert len(names) == 1, names
    reference = np.stack([np.asarray(q)[b, 2 * k : 2 * k + 3] for b in range(4) for k in range(4)])
    np.testing.assert_array_equal(cut.q, reference)
    np.testing.assert_array_equal(cut.qd, -reference)
    (train, held), names = _program_names(lambda: jll.split(data, 0.25, key=jax.random.PRNGKey(0)))
    assert len(names) == 1, names
    rows = sorted(int(x) for x in np.concatenate([train.q[:, 0, 0], held.q[:, 0, 0]]))
    assert rows == [0, 9, 18, 27] and held.q.shape[0] == 1

    states = jll.StateData(q[:, 0], jnp.zeros((4, 1)), -9.81 * jnp.sin(q[:, 0]))
    model = jll.DeLaN(1, 8, 2, key=jax.random.PRNGKey(0))
    with jax.numpy_dtype_promotion("standard"):  # optax mixes int32 step counts with floats
        trained = lambda: jll.train(model, jll.AccelerationLoss(), states, steps=3).train_loss  # noqa: E731
        result, names = _program_names(trained)
    assert not [n for n in names if n and "stack" in n], names
    assert result.shape == (3,) and np.all(np.isfinite(result))


def test_time_tables_and_spectra_compile_once():
    """A time table evaluated eagerly (a plot's ``jax.vmap(u)(grid)``) and a linearization's
    spectral quantities are one program each (before: 38 operations for a cubic spline, 21 for
    the spectra), and so are the closed-loop matrices and ``with_breakpoints``' merge, against
    closed forms: the tables interpolate ``sin`` exactly at its samples and linearly between
    them, the inverted pendulum's eigenvalues are ``±√g``, and a torque-driven pendulum under
    ``u = −kθ − cθ̇`` has ``A + B F = [[0, 1], [−g − k, −c]]``."""
    from jaxlag import analysis, inputs

    jl.compiler_options()  # the once-per-process probe of this XLA's options, not counted below
    ts = jnp.linspace(0.0, 1.0, 6)
    values = jnp.sin(ts)
    midpoints = 0.5 * (ts[1:] + ts[:-1])
    shifted = ts + 0.05  # new times, same shape: no new program
    for table in (
        inputs.ZeroOrderHold(ts, values),
        inputs.PiecewiseLinear(ts, values),
        inputs.CubicSpline(ts, values),
    ):
        at_samples, names = _program_names(lambda table=table: jax.vmap(table)(ts))
        assert len(names) == 1, names
        np.testing.assert_allclose(at_samples, np.sin(ts), rtol=0, atol=1e-15)
        with compilations() as count:
            jax.block_until_ready(jax.vmap(table)(shifted))
        assert count == [0]
    linear = jax.vmap(inputs.PiecewiseLinear(ts, values))(midpoints)
    np.testing.assert_allclose(linear, 0.5 * (np.sin(ts[1:]) + np.sin(ts[:-1])), rtol=0, atol=1e-15)

    upright = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 + 9.81 * jnp.cos(q[0]))
    lin = analysis.linearize(upright, jnp.array([jnp.pi]), jnp.zeros(1))
    spectra, names = _program_names(
        lambda: (lin.eigenvalues, lin.frequencies, lin.growth_rate, lin.is_stable())
    )
    assert len(names) <= 5, names  # eigenvalues, frequencies, growth rate, stability (+ a tolerance array)
    eigenvalues, frequencies, growth, stable = spectra
    np.testing.assert_allclose(eigenvalues, [-np.sqrt(9.81), np.sqrt(9.81)], rtol=1e-12)
    np.testing.assert_allclose(growth, np.sqrt(9.81), rtol=1e-12)
    assert not bool(stable) and lin.stability() == "unstable"
    np.testing.assert_allclose(frequencies, [0.0], atol=1e-12)

    # The closed loop of a torque-driven pendulum θ̈ = −g sin θ + u under u = −k θ − c θ̇ about
    # θ = 0: A + B F = [[0, 1], [−g − k, −c]], one program each for the full and reduced matrix,
    # and merging a table's breakpoints into a controller is one program too (before: 3 each).
    k, c = 4.0, 1.5
    driven = jl.System(
        lambda q, qd: 0.5 * qd[0] ** 2 + 9.81 * jnp.cos(q[0]),
        actuation=lambda q, qd, u: jnp.reshape(u, (1,)),
        control=lambda q, qd: -k * q[0] - c * qd[0],
    )
    closed = analysis.linearize(driven, jnp.zeros(1), jnp.zeros(1))
    (full, reduced), names = _program_names(
        lambda: (closed.closed_loop_matrix, closed.reduced_closed_loop_matrix)
    )
    assert len(names) == 2, names
    expected = np.array([[0.0, 1.0], [-9.81 - k, -c]])
    np.testing.assert_allclose(full, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(reduced, expected, rtol=0, atol=1e-12)  # E = I: no constraint
    hold = inputs.ZeroOrderHold(ts, values)
    line = inputs.PiecewiseLinear(shifted, values)
    base = diffrax.PIDController(rtol=1e-8, atol=1e-8)
    merged, names = _program_names(lambda: inputs.with_breakpoints(base, {"u": hold, "w": line}))
    assert len(names) <= 2, names  # the jump times and the step times
    np.testing.assert_array_equal(merged.jump_ts, ts)
    np.testing.assert_array_equal(merged.step_ts, shifted)


def test_one_shot_analyses_compile_lean_and_agree():
    """An eager ``linearize`` and ``equilibrium`` compile without LLVM's optimizations on the CPU
    (``lean_jit``: they run once per state), inside ``jit`` with the optimized options; both
    give the double pendulum's rest state and its normal modes ``ω² = (2 ∓ √2) g/l``."""
    from jaxlag import analysis
    from jaxlag.analysis import _equilibria, _linearize

    system = jl.systems.double_pendulum()
    guess = jnp.array([0.3, -0.2])
    rest = analysis.equilibrium(system, guess)
    lin = analysis.linearize(system, rest.q)
    if jl.compiler_options():  # on the CPU: the lean programs were the ones compiled
        assert _equilibria._solve._lean and _linearize._linearize._lean
    np.testing.assert_allclose(rest.q, [0.0, 0.0], atol=1e-12)
    g = jl.systems.default_args(jl.systems.double_pendulum)["g"]  # unit masses and rods
    expected = np.sqrt(np.array([2.0 - np.sqrt(2.0), 2.0 + np.sqrt(2.0)]) * g)
    np.testing.assert_allclose(lin.frequencies, expected, rtol=1e-10)
    optimized = eqx.filter_jit(lambda q: analysis.linearize(system, q).state_matrix)(rest.q)
    np.testing.assert_allclose(lin.state_matrix, optimized, rtol=1e-12, atol=1e-12)
    jitted_rest = eqx.filter_jit(lambda q: analysis.equilibrium(system, q).q)(guess)
    np.testing.assert_allclose(jitted_rest, rest.q, atol=1e-12)
