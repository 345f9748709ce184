"""jl.fit's programs: the lean and the optimized linearization agree, the fit chooses between
them by its size alone (and switches when the integrator's steps show a larger fit than its save
times did), the rolled initial projection is the unrolled one, and the host-side bookkeeping
compiles nothing (no eager ``jax.numpy`` programs of the parameters)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
from jaxlag._conventions import wrap_state_function
from jaxlag._fit import fit as fitting
from jaxlag._fit import model as fit_model
from jaxlag._stabilization import projection_with_residuals


def sphere(q, qd, args):  # the README demo: a particle on a sphere of radius R, polar coordinates
    return 0.5 * args["m"] * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2) - args["m"] * args["g"] * q[0] * jnp.cos(
        q[1]
    )


def on_sphere(q, args):
    return jnp.array([q[0] - args["R"]])


def camera(q, qd):
    return q[0] * jnp.array([jnp.sin(q[1]), jnp.cos(q[1])])


SYSTEM = jl.System(sphere, holonomic=on_sphere)
TRUE = {"m": 1.0, "g": 9.81, "R": 2.0}
Q0, QD0 = jnp.array([2.0, 0.05]), jnp.zeros(2)
TS = np.linspace(0.0, 1.5, 61)
TRANSFORMS: dict[str, jl.Positive | jl.Bounded] = {"g": jl.Positive(), "R": jl.Positive()}


def _experiment():
    q = np.asarray(jl.simulate(SYSTEM, Q0, QD0, TS, args=TRUE).q)
    observed = q[:, :1] * np.stack([np.sin(q[:, 1]), np.cos(q[:, 1])], axis=1)
    return jl.Experiment(
        TS, observed + 1e-3 * np.random.default_rng(0).standard_normal(observed.shape), Q0, QD0
    )


def _problem(experiment):
    observe = wrap_state_function(camera, "observation function")
    return fitting._problem(
        SYSTEM, {"g": 8.0, "R": 2.4}, experiment, observe, {"m": 1.0}, dict(TRANSFORMS), None, False,
        jl.Shooting(), jl.SimulateOptions(),
    )  # fmt: skip


def test_lean_and_optimized_linearizations_agree():
    problem = _problem(_experiment())
    args = (problem.model, problem.free, problem.data, problem.fixed_states)
    assert fit_model.Linearizer(problem.model, problem.data, problem.fixed_states, problem.free).lean
    optimized = fit_model.residuals_and_jacobian(*args, lean=False)
    cheap = fit_model.residuals_and_jacobian(*args, lean=True)
    np.testing.assert_allclose(cheap.residuals, optimized.residuals, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(cheap.jacobian, optimized.jacobian, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(cheap.point, optimized.point)


def test_fit_switches_to_the_optimized_program_by_the_integrators_steps(monkeypatch):
    experiment = _experiment()
    reference = jl.fit(
        SYSTEM, {"g": 8.0, "R": 2.4}, experiment, observe=camera, args={"m": 1.0}, transforms=TRANSFORMS
    )
    calls = []
    for name in ("_linearize", "_linearize_lean"):
        program = getattr(fit_model, name)
        monkeypatch.setattr(fit_model, name, lambda *a, _p=program, _n=name: calls.append(_n) or _p(*a))
    # Work per step: (2 free scalars + 1) × 2² coordinates = 12. The save times allow the lean
    # program (61 × 12 ≤ 4 × LEAN_WORK), the integrator's steps (more than 61 / 4) exceed
    # LEAN_WORK: the first call is lean, the others optimized.
    monkeypatch.setattr(fit_model, "LEAN_WORK", len(TS) * 12 // 4)
    switched = jl.fit(
        SYSTEM, {"g": 8.0, "R": 2.4}, experiment, observe=camera, args={"m": 1.0}, transforms=TRANSFORMS
    )
    assert calls[0] == "_linearize_lean" and set(calls[1:]) == {"_linearize"}, calls
    for name in ("g", "R"):
        np.testing.assert_allclose(switched.params[name], reference.params[name], rtol=1e-9)
        np.testing.assert_allclose(switched.standard_errors[name], reference.standard_errors[name], rtol=1e-6)


def test_rolled_projection_is_the_unrolled_one():
    args = {"m": 1.0, "g": 9.81, "R": 2.4}
    q0, qd0 = jnp.array([2.0, 0.3]), jnp.array([0.5, 0.1])
    rolled = jax.jit(lambda q, qd: fit_model._projection_with_residual(SYSTEM, q, qd, 0.0, args))(q0, qd0)
    unrolled = jax.jit(lambda q, qd: projection_with_residuals(SYSTEM, q, qd, 0.0, args))(q0, qd0)
    for a, b in zip(rolled, unrolled[:3]):
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("transform", [jl.Positive(), jl.Bounded(0.5, 20.0)])
def test_starting_point_and_standard_errors_on_the_host(transform):
    compiled = []

    def listen(event: str, duration_secs: float, **kwargs: str | int) -> None:
        if event == "/jax/core/compile/backend_compile_duration":
            compiled.append(str(kwargs.get("fun_name", "")))

    spec = fit_model.ParamSpec(("g", "k"), ((), (2,)))
    model = fit_model.Model(SYSTEM, camera, {"g": transform}, spec, segments=1, estimate_initial_state=False,
                            simulation={})  # fmt: skip
    physical = {"g": np.asarray(9.81), "k": np.asarray([1.0, 2.0])}
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        flat = fit_model.unconstrained(model, physical)
        unravelled = spec.unravel(np.asarray([1.0, 2.0, 3.0]))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert not compiled, compiled  # NumPy on the host: no program
    assert isinstance(flat, jax.Array) and flat.shape == (3,)
    np.testing.assert_allclose(np.asarray(model.physical(flat)["g"]), 9.81, rtol=1e-14)
    np.testing.assert_array_equal(unravelled["k"], [2.0, 3.0])
    assert unravelled["g"].shape == ()
