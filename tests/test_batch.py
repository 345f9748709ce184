"""simulate_batch: vmapped batches equal the loop, sharding equals the unsharded run, no recompiles."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
from jaxlag import simulate_batch

jax.config.update("jax_enable_x64", True)

TS = jnp.linspace(0.0, 2.0, 21)
TRACES = []


def pendulum(q, qd, args):
    TRACES.append(1)  # runs once per trace, never per step
    return 0.5 * args["l"] ** 2 * qd[0] ** 2 + args["g"] * args["l"] * jnp.cos(q[0])


PENDULUM = jl.System(pendulum)


class CompileCounter:
    """Counts XLA backend compilations (``jax.monitoring`` duration events)."""

    EVENT = "/jax/core/compile/backend_compile_duration"

    def __init__(self):
        self.count = 0

    def __call__(self, event, duration, **kwargs):
        if event == self.EVENT:
            self.count += 1

    def __enter__(self):
        jax.monitoring.register_event_duration_secs_listener(self)
        return self

    def __exit__(self, *exc):
        jax.monitoring.unregister_event_duration_listener(self)


def test_batch_of_states_and_parameters_equals_the_loop_and_does_not_recompile():
    q0s = jnp.array([[0.1], [0.7], [1.5], [2.9]])
    qd0s = jnp.array([[0.0], [0.3], [-0.2], [0.1]])
    gs = jnp.array([1.0, 9.81, 20.0, 3.0])
    args = {"g": gs, "l": 1.3}
    batch = simulate_batch(PENDULUM, q0s, qd0s, TS, args=args, args_axes={"g": 0, "l": None})
    assert batch.q.shape == (4, 21, 1) and batch.energy.shape == (4, 21)
    for i in range(4):
        single = jl.simulate(PENDULUM, q0s[i], qd0s[i], TS, args={"g": gs[i], "l": 1.3})
        np.testing.assert_allclose(batch.q[i], single.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.qd[i], single.qd, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.energy[i], single.energy, rtol=1e-13)

    # Later calls with new states and new parameter values (JAX arrays, NumPy arrays, Python
    # floats) neither retrace the Lagrangian nor compile anything in XLA. (The first call with a
    # NumPy input compiles a tiny host-to-device conversion once, so each input kind is seen once
    # before counting.)
    def call_batch(scale):
        out = simulate_batch(
            PENDULUM,
            np.asarray(q0s) * scale,
            qd0s + scale,
            TS,
            args={"g": gs * scale, "l": 0.7 * scale},
            args_axes={"g": 0, "l": None},
        )
        return jax.block_until_ready(out)

    def call_single(scale):
        out = jl.simulate(
            PENDULUM,
            [0.4 * scale],
            np.array([0.2]),
            TS,
            args={"g": np.float64(5.0 * scale), "l": 2.0 * scale},
        )
        return jax.block_until_ready(out)

    call_batch(1.0), call_single(1.0)
    traces = len(TRACES)
    with CompileCounter() as compiles:
        for scale in (0.5, 0.8):
            again = call_batch(scale)
            call_single(scale)
    assert len(TRACES) == traces
    assert compiles.count == 0
    expected = jl.simulate(PENDULUM, q0s[2] * 0.8, qd0s[2] + 0.8, TS, args={"g": gs[2] * 0.8, "l": 0.7 * 0.8})
    np.testing.assert_allclose(again.q[2], expected.q, rtol=0, atol=1e-12)


def test_shared_state_batched_parameters_and_all_leaves_batched():
    args = {"g": jnp.array([4.0, 9.81]), "l": jnp.array([1.0, 2.0])}
    all_batched = simulate_batch(PENDULUM, jnp.array([1.0]), jnp.zeros(1), TS, args=args, args_axes=0)
    assert all_batched.q.shape == (2, 21, 1)
    single = jl.simulate(PENDULUM, [1.0], [0.0], TS, args={"g": 9.81, "l": 2.0})
    np.testing.assert_allclose(all_batched.q[1], single.q, rtol=0, atol=1e-12)


def test_bad_batches_are_rejected_with_a_message():
    args = {"g": jnp.array([4.0, 9.81, 1.0]), "l": 1.0}
    with pytest.raises(ValueError, match="Inconsistent batch sizes"):
        simulate_batch(PENDULUM, jnp.ones((2, 1)), jnp.zeros(1), TS, args=args, args_axes={"g": 0, "l": None})
    with pytest.raises(ValueError, match="Nothing to batch"):
        simulate_batch(PENDULUM, jnp.ones(1), jnp.zeros(1), TS, args={"g": 9.81, "l": 1.0})
    with pytest.raises(ValueError, match="is a scalar"):
        simulate_batch(PENDULUM, jnp.ones((2, 1)), jnp.zeros(1), TS, args={"g": 9.81, "l": 1.0}, args_axes=0)
    with pytest.raises(ValueError, match="0 .* or None"):
        simulate_batch(PENDULUM, jnp.ones((2, 1)), jnp.zeros(1), TS, args=args, args_axes=1)
    with pytest.raises(ValueError, match="shape \\(B, n\\)"):
        simulate_batch(PENDULUM, jnp.ones((2, 1, 1)), jnp.zeros(1), TS, args=args)
    with pytest.raises(TypeError, match="sharding"):
        simulate_batch(PENDULUM, jnp.ones((2, 1)), jnp.zeros(1), TS, args={"g": 9.81, "l": 1.0}, sharding=4)


def test_sharded_batch_on_four_host_devices_equals_unsharded():
    """The suite runs with 4 CPU devices (conftest: jax_num_cpu_devices): a batch sharded over
    them equals the unsharded batch, events included, also when it has to be padded."""

    assert jax.device_count() == 4, jax.devices()
    R = 2.0

    def lagrangian(q, qd, args):  # particle outside a sphere, polar (r, θ) from the top
        r, th = q
        rd, thd = qd
        return 0.5 * (rd**2 + r**2 * thd**2) - args["g"] * r * jnp.cos(th)

    def on_sphere(q, args):
        return jnp.array([q[0] - args["R"]])

    system = jl.System(lagrangian, holonomic=on_sphere, unilateral=0)  # r − R ≥ 0: it lets go
    ts = jnp.linspace(0.0, 1.6, 9)
    theta0 = jnp.linspace(0.2, 0.55, 8)
    q0 = jnp.stack([jnp.full_like(theta0, R), theta0], axis=1)
    args = {"g": 9.81, "R": R}

    events = jl.Events(max_segments=3)
    plain = simulate_batch(system, q0, jnp.zeros(2), ts, args=args, events=events)
    sharded = simulate_batch(system, q0, jnp.zeros(2), ts, args=args, events=events, sharding="auto")
    # 6 members are padded to 8 (a multiple of the 4 devices): the same program as above.
    padded = simulate_batch(system, q0[:6], jnp.zeros(2), ts, args=args, events=events, sharding="auto")

    assert sharded.q.shape == plain.q.shape == (8, 9, 2) and padded.q.shape == (6, 9, 2)
    devices = {shard.device for shard in sharded.q.addressable_shards}
    assert len(devices) == 4, devices
    assert [s.data.shape for s in sharded.q.addressable_shards] == [(2, 9, 2)] * 4
    assert sharded.q.sharding.spec[0] == "batch", sharded.q.sharding
    for name in ("q", "qd"):
        np.testing.assert_allclose(getattr(sharded, name), getattr(plain, name), rtol=0, atol=1e-12)
        np.testing.assert_allclose(getattr(padded, name), getattr(plain, name)[:6], rtol=0, atol=1e-12)
    np.testing.assert_allclose(sharded.events.time, plain.events.time, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(sharded.events.kind, plain.events.kind)
    # Each member lets go of the sphere where cos θ = (2/3) cos θ0.
    assert np.all(np.asarray(sharded.events.kind[:, 0]) == 1)
    np.testing.assert_allclose(sharded.events.q[:, 0, 1], np.arccos(2 / 3 * np.cos(theta0)), atol=1e-8)


@pytest.mark.parametrize("kind", ["unconstrained", "unilateral"])
def test_memory_grows_linearly_in_the_batch(kind):
    """XLA's buffer assignment (``memory_analysis``, deterministic, not a timing) of the compiled
    batched call grows linearly in B, with a per-member cost bounded by a small multiple of what one
    member's saved outputs need.

    How exact "linearly" can be checked depends on the backend. On CPU the bytes per added member
    are the same from B = 16 → 32 as from 32 → 64 up to buffer alignment (892 B both; 2652 B and
    2646 B with events and the per-member failure record). On a
    GPU XLA picks fusions, reduction tilings and their scratch buffers per shape, which adds to the
    temporaries a term that changes with B but not in proportion to it (the exact CPU check failed
    on an H100). There only the properties that do not depend on those choices are asserted: the
    arguments and outputs are exactly linear in B; the temporaries grow by at least one ODE state
    (q, q̇) per added member, since the solver loop carries every member's state; and the total
    grows by at most 20 × one member's saved outputs per added member, at B = 32, 64 and 128.
    """
    if kind == "unconstrained":
        system, n = PENDULUM, 1
        q0, qd0, kwargs = jnp.array([0.5]), jnp.array([0.0]), {"args": {"g": 9.81, "l": 1.0}}
    else:  # a particle released from a sphere: constrained, with a release event
        system = jl.System(
            lambda q, qd: 0.5 * jnp.sum(qd**2) - 9.81 * q[1],
            lambda q: jnp.array([jnp.sqrt(q[0] ** 2 + q[1] ** 2) - 1.0]),
            unilateral=0,
        )
        n, kwargs = 2, {}
        q0, qd0 = jnp.array([jnp.sin(0.2), jnp.cos(0.2)]), jnp.zeros(2)

    def memory(batch):
        states = jnp.tile(q0, (batch, 1)) * (1.0 + 0.01 * jnp.arange(batch, dtype=float))[:, None]
        run = jax.jit(lambda s: simulate_batch(system, s, qd0, TS, **kwargs).q)
        stats = run.lower(states).compile().memory_analysis()
        return {
            "temp": stats.temp_size_in_bytes,
            "arguments": stats.argument_size_in_bytes,
            "outputs": stats.output_size_in_bytes,
        }

    saved = TS.shape[0] * n * 8  # one member's saved q, float64
    state = n * 8  # one member's initial positions, float64
    # From 32 members: below that a constant of XLA's buffer assignment still shifts (with events,
    # 2556 B per member from 16 to 32, then 2590, 2592, 2592 B up to 256).
    sizes = (32, 64, 128) if jax.default_backend() == "cpu" else (32, 64, 128, 256)
    stats = {batch: memory(batch) for batch in sizes}
    total = {batch: sum(s.values()) for batch, s in stats.items()}
    for batch, s in stats.items():  # exact on every backend: these buffers are the arrays themselves
        assert s["arguments"] == batch * state, (batch, s)
        assert s["outputs"] == batch * saved, (batch, s)

    if jax.default_backend() == "cpu":
        per_member_low = (total[64] - total[32]) / 32
        per_member_high = (total[128] - total[64]) / 64
        assert per_member_low > 0
        # Linear up to XLA's 64-byte buffer alignment: padding depends on how many small (scalar
        # per member) buffers a batch needs, a few hundred bytes in all, not on B. Measured:
        # 892 B == 892 B unconstrained; 2652 B vs 2646 B with events (second difference 192 B).
        second_difference = (total[128] - total[64]) - 2 * (total[64] - total[32])
        assert abs(second_difference) <= 0.01 * (total[128] - total[64]), (per_member_low, per_member_high)
        assert per_member_high < 20 * saved  # measured: 892 B (5.3×) and 2592 B (7.7×)
    else:
        for batch in sizes[1:]:
            added = batch - 32
            assert stats[batch]["temp"] - stats[32]["temp"] >= added * 2 * state, (batch, stats)
            assert total[batch] - total[32] <= added * 20 * saved, (batch, total)


def test_batch_checks_on_the_host_name_the_member():
    """Concrete batches are checked on the host (the program returns the diagnostics): a member
    off the constraint manifold is named with simulate's message, as are bad save times; under
    an enclosing jit the checks are compiled in and raise too."""
    system = jl.System(
        lambda q, qd, args: 0.5 * (qd @ qd) - args["g"] * q[1],
        holonomic=lambda q, args: jnp.array([q @ q - 1.0]),
    )
    q0s = jnp.array([[0.0, -1.0], [0.6, -0.8], [0.6, -0.9], [1.0, 0.0]])
    ts = jnp.linspace(0.0, 0.5, 6)
    args = {"g": 9.81}
    with pytest.raises(
        ValueError,
        match=r"1 of 4 batch members failed \(first: member \[2\]\)"
        r".*(constraint|manifold|violat)",
    ):
        jl.simulate_batch(system, q0s, jnp.zeros(2), ts, args=args)
    with pytest.raises(ValueError, match="strictly increasing"):
        jl.simulate_batch(system, q0s[:2], jnp.zeros(2), ts[::-1], args=args)
    good = jl.simulate_batch(system, q0s[jnp.array([0, 1, 3])], jnp.zeros(2), ts, args=args)
    np.testing.assert_allclose(jnp.sum(good.q**2, axis=-1), 1.0, atol=1e-9)
    with pytest.raises(Exception, match=r"off the constraint manifold"):  # compiled: the cause
        jax.block_until_ready(
            jax.jit(lambda q: jl.simulate_batch(system, q, jnp.zeros(2), ts, args=args).q)(q0s)
        )
    # Checks(initial_state=False) is respected: no diagnostics, the member just runs.
    traj = jl.simulate_batch(
        system, q0s, jnp.zeros(2), ts, args=args, checks=jl.Checks(initial_state=False), throw=False
    )
    assert traj.q.shape == (4, 6, 2)


def test_batch_method_objects():
    """The method is an object: jl.Vmap(), jl.Ensemble(backend=...) or None (chosen: vmap on
    CPU); strings and unknown backends are refused; simulate's options are keywords."""
    q0s = jnp.array([[0.1], [0.7], [1.5]])
    args = {"g": 9.81, "l": 1.3}
    options = dict(args=args, stepsize_controller=diffrax.ConstantStepSize(), dt0=0.01)
    assert issubclass(jl.Vmap, jl.AbstractBatchMethod) and issubclass(jl.Ensemble, jl.AbstractBatchMethod)
    assert jl.Ensemble().backend == "auto"
    vmapped = simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, method=jl.Vmap(), **options)
    if jax.default_backend() == "cpu":  # method=None is vmap on CPU: the same program
        chosen = simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, **options)
        np.testing.assert_array_equal(chosen.q, vmapped.q)
    for backend in ("auto", "xla"):
        ensemble = simulate_batch(
            PENDULUM, q0s, jnp.zeros(1), TS, method=jl.Ensemble(backend=backend), **options
        )
        # The ensemble loop's Trajectory has vmap's per-member failure record.
        np.testing.assert_array_equal(ensemble.failure.code, vmapped.failure.code)
        np.testing.assert_allclose(ensemble.q, vmapped.q, rtol=0, atol=1e-12)
    with pytest.raises(TypeError, match=r"method must be jl\.Vmap\(\), jl\.Ensemble\(\.\.\.\) or None"):
        simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, method="vmap")
    with pytest.raises(TypeError, match=r"method must be"):
        simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, method=jl.Vmap)
    with pytest.raises(ValueError, match=r"Ensemble backend must be one of 'auto', 'xla', 'pallas'"):
        jl.Ensemble(backend="cuda")
    with pytest.raises(TypeError, match="unexpected keyword"):
        simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, backend="xla")
    with pytest.raises(TypeError, match="unexpected keyword"):
        simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, max_segments=3)
    with pytest.raises(TypeError, match=r"projection must be jl\.Projection\(\) or None"):
        simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, projection="auto")
    with pytest.raises(TypeError, match=r"events must be a jl\.Events"):
        simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, events="crossing")
    with pytest.raises(TypeError, match=r"checks must be a jl\.Checks"):
        simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, checks=None)


def test_batch_takes_simulate_option_objects():
    """Events and Checks reach every member, by either method where it applies."""
    q0s = jnp.array([[0.3], [0.6]])
    args = {"g": 9.81, "l": 1.0}
    crossing = jl.Event(lambda q, qd: q[0], terminal=False)
    batch = simulate_batch(
        PENDULUM, q0s, jnp.zeros(1), TS, args=args, events=jl.Events(crossing, max_segments=3)
    )
    assert batch.events.time.shape == (2, 3)
    for i in range(2):
        single = jl.simulate(
            PENDULUM, q0s[i], jnp.zeros(1), TS, args=args, events=jl.Events(crossing, max_segments=3)
        )
        np.testing.assert_allclose(batch.events.time[i], single.events.time, rtol=0, atol=1e-12)
        np.testing.assert_allclose(batch.q[i], single.q, rtol=0, atol=1e-12)
    # A plain list of events is accepted as by simulate; the ensemble loop refuses events.
    listed = simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, events=[crossing])
    assert listed.events.time.shape == (2, 8)
    with pytest.raises(ValueError, match=r"Event.*method=jl\.Vmap\(\)"):
        simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, events=[crossing], method=jl.Ensemble())
    # Checks: a member off the circle is refused by both methods unless the check is skipped.
    system = jl.System(
        lambda q, qd, args: 0.5 * (qd @ qd) - args["g"] * q[1],
        holonomic=lambda q, args: jnp.array([q @ q - 1.0]),
    )
    q0s = jnp.array([[0.6, -0.8], [0.6, -0.81]])
    ts = jnp.linspace(0.0, 0.5, 3)
    for method in (jl.Vmap(), jl.Ensemble()):
        with pytest.raises(Exception, match="off the constraint manifold"):
            jax.block_until_ready(
                simulate_batch(system, q0s, jnp.zeros(2), ts, args={"g": 9.81}, method=method).q
            )
        out = simulate_batch(
            system,
            q0s,
            jnp.zeros(2),
            ts,
            args={"g": 9.81},
            method=method,
            checks=jl.Checks(initial_state=False),
        )
        assert out.q.shape == (2, 3, 2)
        loose = simulate_batch(
            system,
            q0s,
            jnp.zeros(2),
            ts,
            args={"g": 9.81},
            method=method,
            checks=jl.Checks(constraint_tolerance=0.1),
        )
        np.testing.assert_allclose(loose.q, out.q, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- solver/controller
def harmonic(q, qd):
    return 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2


HARMONIC = jl.System(harmonic)
ADAPTIVE = diffrax.PIDController(rtol=1e-8, atol=1e-8)
NO_ESTIMATE = r"cannot be used with an adaptive step-size controller"
FIX = (
    r"Pass stepsize_controller=diffrax\.ConstantStepSize\(\) with a step dt0=\.\.\., or a solver "
    r"with an error estimate, such as diffrax\.Tsit5\(\)"
)


def test_solver_without_error_estimate_needs_constant_steps_everywhere():
    # Before: solver=jl.RK4() under the default PIDController had an error estimate of 0, so every
    # step was accepted and grown ×10: 4 steps over [0, 10], |q − cos t| = 196, no error.
    # diffrax.Euler() raised diffrax's RuntimeError "Cannot use adaptive step sizes with a solver
    # that does not provide error estimates." from inside the trace, with no fix named.
    ts = jnp.linspace(0.0, 10.0, 3)
    q0, qd0 = jnp.array([1.0]), jnp.array([0.0])
    states = jnp.ones((2, 1)), jnp.zeros((2, 1))
    controllers = [None, ADAPTIVE, diffrax.ClipStepSizeController(ADAPTIVE)]
    for solver, reason in [(jl.RK4(), "RK4 has no embedded method"), (diffrax.Euler(), "Euler returns no")]:
        for controller in controllers:
            options = dict(solver=solver, stepsize_controller=controller)
            here = r"\(here the default, PIDController\)" if controller is None else r"\(here PIDController\)"
            with pytest.raises(
                ValueError, match=r"adaptive step-size controller " + here + ": " + reason + ".*" + FIX
            ):
                jl.simulate(HARMONIC, q0, qd0, ts, **options)
            with pytest.raises(ValueError, match=NO_ESTIMATE):  # at trace time, inside jit
                jax.jit(lambda q: jl.simulate(HARMONIC, q, qd0, ts, **options).q)(q0)
            with pytest.raises(ValueError, match=NO_ESTIMATE):
                jax.vmap(lambda q: jl.simulate(HARMONIC, q, qd0, ts, **options).q)(states[0])
            for method in (jl.Vmap(), jl.Ensemble()):
                with pytest.raises(ValueError, match=NO_ESTIMATE + ".*" + reason):
                    jl.simulate_batch(HARMONIC, *states, ts, method=method, **options)
    experiment = jl.Experiment(ts, jnp.cos(ts)[:, None], q0, qd0)
    stiffness = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 - 0.5 * args["k"] * q[0] ** 2)
    with pytest.raises(ValueError, match=NO_ESTIMATE + ".*RK4 has no embedded method"):
        jl.fit(stiffness, {"k": 1.1}, experiment, solver=jl.RK4())


def test_solvers_with_an_error_estimate_or_constant_steps_are_accepted():
    from jaxlag._solver.validation import solver_controller_message

    accepted = [diffrax.Tsit5(), diffrax.Heun(), diffrax.Midpoint(), diffrax.Ralston(), diffrax.Bosh3()]
    accepted += [diffrax.HalfSolver(jl.RK4()), diffrax.HalfSolver(diffrax.Euler())]
    for solver in accepted:
        assert solver_controller_message(solver, ADAPTIVE) is None, solver
    for solver in (jl.RK4(), diffrax.Euler(), diffrax.SemiImplicitEuler()):
        assert solver_controller_message(solver, ADAPTIVE) is not None
        for controller in (diffrax.ConstantStepSize(), diffrax.StepTo(ts=jnp.linspace(0.0, 1.0, 3))):
            assert solver_controller_message(solver, controller) is None
    # What the messages suggest works, to the closed form q = cos t (RK4 at dt = 0.01: global
    # error 4.5e-10 over [0, 10]; step doubling at rtol = atol = 1e-8: 1.4e-7, 142 steps).
    ts = jnp.linspace(0.0, 10.0, 3)
    constant = jl.simulate(
        HARMONIC, jnp.array([1.0]), jnp.array([0.0]), ts, solver=jl.RK4(),
        stepsize_controller=diffrax.ConstantStepSize(), dt0=0.01,
    )  # fmt: skip
    np.testing.assert_allclose(constant.q[:, 0], jnp.cos(ts), rtol=0, atol=1e-9)
    halved = jl.simulate(
        HARMONIC, jnp.array([1.0]), jnp.array([0.0]), ts, solver=diffrax.HalfSolver(jl.RK4()),
        stepsize_controller=ADAPTIVE,
    )  # fmt: skip
    np.testing.assert_allclose(halved.q[:, 0], jnp.cos(ts), rtol=0, atol=1e-6)


def test_simulate_options_are_simulates_keywords():
    """jl.SimulateOptions names every keyword option of jl.simulate (all but ``args``), and a
    dict of them built once goes to simulate and simulate_batch alike."""
    import inspect
    import typing

    keywords = {
        p.name for p in inspect.signature(jl.simulate).parameters.values() if p.kind is p.KEYWORD_ONLY
    }
    assert set(typing.get_type_hints(jl.SimulateOptions)) == keywords - {"args"}
    options: jl.SimulateOptions = {"stepsize_controller": diffrax.ConstantStepSize(), "dt0": 0.01}
    args = {"g": 9.81, "l": 1.0}
    q0s = jnp.array([[0.2], [0.4]])
    batch = simulate_batch(PENDULUM, q0s, jnp.zeros(1), TS, args=args, **options)
    one = jl.simulate(PENDULUM, q0s[1], jnp.zeros(1), TS, args=args, **options)
    np.testing.assert_allclose(batch.q[1], one.q, rtol=0, atol=1e-13)
