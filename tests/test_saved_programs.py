"""Saved programs (jaxlag.saved_programs): a second process loads simulate's solve and the
forward-sensitivity program of jax.grad instead of tracing them, with bit-identical results; a
change to anything that determines a program (a constant in L, a closed-over array, a shape, an
option) is a different fingerprint; calls the fingerprint cannot describe, and calls inside
jit/vmap, run through jax.jit as before."""

import json
import os
import shutil
import subprocess
import sys
import textwrap

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxlag as jl
from jaxlag import saved_programs
from jaxlag import simulate as _simulate_module  # noqa: F401 - the module, for its programs

_solve = sys.modules["jaxlag.simulate"]._solve
_solve_with_tangents = sys.modules["jaxlag.simulate"]._solve_with_tangents
_evaluate = sys.modules["jaxlag.trajectory"]._evaluate
PROGRAMS = (_solve, _solve_with_tangents, _evaluate)

SCRIPT = textwrap.dedent('''
    import json, os, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import jaxlag as jl
    from jaxlag import saved_programs

    SCALE = np.array([1.0, float(os.environ["SCALE"])])   # closed over by L

    def lagrangian(q, qd, args):
        r, th = q
        rd, thd = qd
        m, g = args["m"], args["g"]
        kinetic = 0.5 * m * (rd**2 + r**2 * thd**2)
        return kinetic - m * g * r * jnp.cos(th) * SCALE[1] + LITERAL * th**2

    LITERAL = float(os.environ["LITERAL"])
    system = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]))
    args = {"m": 1.0, "g": 9.81, "R": 2.0}
    traj = jl.simulate(system, jnp.array([2.0, 0.1]), jnp.zeros(2), jnp.linspace(0, 2, 21),
                       args=args)
    loss = lambda a: jnp.sum(jl.simulate(system, jnp.array([2.0, 0.1]), jnp.zeros(2),
                                         jnp.linspace(0, 1, 11), args=a).q[:, 1] ** 2)
    grad = jax.grad(loss)(args)
    # Sliding off the sphere (a unilateral constraint): a segmented run whose root finder
    # factorizes with LAPACK, which a loaded executable needs initialized.
    contact = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]),
                        unilateral=0)
    slide = jl.simulate(contact, jnp.array([2.0, 0.1]), jnp.zeros(2), jnp.linspace(0, 2, 21),
                        args=args)
    print("RESULT " + json.dumps({
        "slide": np.asarray(slide.q).tolist(), "release": float(slide.events.time[0]),
        "q": np.asarray(traj.q).tolist(), "multipliers": np.asarray(traj.multipliers).tolist(),
        "grad": {k: float(v) for k, v in grad.items()},
        "statistics": dict(saved_programs.statistics)}))
''')


def _run(cache_home, literal="0.0", scale="1.0", cache="1"):
    env = dict(os.environ, XDG_CACHE_HOME=str(cache_home), JAXLAG_COMPILATION_CACHE=cache,
               LITERAL=literal, SCALE=scale)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def test_a_second_process_loads_the_programs_and_a_changed_one_does_not(tmp_path):
    reference = _run(tmp_path / "unused", cache="0")  # no cache at all
    assert reference["statistics"] == {}
    first = _run(tmp_path)
    # simulate's solve, traj.multipliers, the tangent solve of jax.grad, the segmented run.
    assert first["statistics"] == {"compiled": 4, "saved": 4}
    assert not any("saved_" in name for name in os.listdir(tmp_path / "jaxlag" / "jax"))
    second = _run(tmp_path)
    assert second["statistics"] == {"loaded": 4}
    # Bit for bit: the same executables.
    for run in (first, second):
        assert run["slide"] == reference["slide"] and run["release"] == reference["release"]
        assert run["q"] == reference["q"]
        assert run["multipliers"] == reference["multipliers"]
        assert run["grad"] == reference["grad"]
    # Saved programs removed, JAX's own cache kept: compiled again (JAX's cache does not hold
    # them, and an executable it loads is never saved: its re-serialized form lacks the machine
    # code of its fusions, "Function convert_multiply_fusion not found" in the process after).
    shutil.rmtree(tmp_path / "jaxlag" / "programs")
    third = _run(tmp_path)
    assert third["statistics"] == {"compiled": 4, "saved": 4}
    fourth = _run(tmp_path)
    assert fourth["statistics"] == {"loaded": 4}
    for run in (third, fourth):
        assert run["slide"] == reference["slide"] and run["q"] == reference["q"]
        assert run["grad"] == reference["grad"]
    # A different constant in L and a different closed-over array: new programs, new results.
    for changed in (_run(tmp_path, literal="0.5"), _run(tmp_path, scale="1.1")):
        assert changed["statistics"] == {"compiled": 4, "saved": 4}
        assert changed["q"] != reference["q"] and changed["grad"] != reference["grad"]


GUARD_SCRIPT = textwrap.dedent('''
    import contextlib, json, os
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import jaxlag as jl
    from jaxlag import saved_programs

    if os.environ["PROTECTION"] in ("old", "none"):  # as with a JAX that ignores the override
        saved_programs._no_jax_cache_writes = contextlib.nullcontext
    if os.environ["PROTECTION"] == "none":  # as session 8's jaxlag: saves what JAX's cache loads
        saved_programs._compiling_for_saving = lambda: contextlib.nullcontext(
            type("Watch", (), {"loaded_by_jax": False}))
    system = jl.System(lambda q, qd: 0.5 * qd @ qd - 9.81 * q[1],
                       holonomic=lambda q: jnp.array([q @ q - 1.0]))
    traj = jl.simulate(system, jnp.array([0.6, -0.8]), jnp.zeros(2), jnp.linspace(0, 1, 5))
    print("RESULT " + json.dumps({"q": np.asarray(traj.q).tolist(),
                                  "statistics": dict(saved_programs.statistics)}))
''')


def test_an_executable_loaded_by_jax_cache_is_never_saved_and_a_broken_file_is_replaced(
        tmp_path):
    """Should JAX's cache hold a saved program's executable (an older jaxlag wrote it, or a JAX
    ignores the override), the executable it loads is used but not saved: re-serialized, it
    fails to run in the next process. A file saved so anyway (by session 8's jaxlag) fails its
    first call: it is deleted and the program compiled, with the same result."""
    def run(protection):
        env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path), JAXLAG_COMPILATION_CACHE="1",
                   PROTECTION=protection)
        env.pop("JAX_COMPILATION_CACHE_DIR", None)
        out = subprocess.run([sys.executable, "-c", GUARD_SCRIPT], capture_output=True,
                             text=True, env=env, timeout=600)
        assert out.returncode == 0, out.stderr[-3000:]
        return json.loads(out.stdout.split("RESULT ")[-1])

    programs = tmp_path / "jaxlag" / "programs"
    first = run("old")
    assert first["statistics"] == {"compiled": 1, "saved": 1}
    assert any("saved_solve" in name for name in os.listdir(tmp_path / "jaxlag" / "jax"))
    shutil.rmtree(programs)
    assert run("none")["statistics"] == {"compiled": 1, "saved": 1}  # a broken file
    healed = run("full")
    assert healed["statistics"] == {"loaded": 1, "discarded": 1, "compiled": 1,
                                    "loaded_by_jax_cache": 1}
    assert healed["q"] == first["q"] and not os.listdir(programs)
    again = run("full")  # nothing saved, so the next process too takes JAX's entry, and runs
    assert again["statistics"] == {"compiled": 1, "loaded_by_jax_cache": 1}
    assert again["q"] == first["q"] and not os.listdir(programs)


@pytest.fixture
def program_cache(tmp_path, monkeypatch):
    """Saved programs switched on in a fresh directory, and this process's memory cleared."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setenv("JAXLAG_COMPILATION_CACHE", "1")
    monkeypatch.delenv("JAXLAG_PROGRAM_CACHE", raising=False)
    saved_programs.statistics.clear()
    for program in PROGRAMS:
        program._memory.clear()
    yield tmp_path / "jaxlag" / "programs"
    for program in PROGRAMS:
        program._memory.clear()
    saved_programs.statistics.clear()


def _pendulum(scale=1.0):
    return jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 + scale * args["g"] * jnp.cos(q[0]))


def _simulate(system, q0=0.5, **kwargs):
    return jl.simulate(system, jnp.array([q0]), jnp.zeros(1), jnp.linspace(0.0, 1.0, 6),
                       args={"g": 9.81}, **kwargs)


def test_loaded_program_gives_the_same_trajectory_structure_and_values(program_cache):
    system = _pendulum()
    first = _simulate(system)
    assert dict(saved_programs.statistics) == {"compiled": 1, "saved": 1}
    assert len(os.listdir(program_cache)) == 1
    _solve._memory.clear()  # as a new process would
    second = _simulate(system)
    assert saved_programs.statistics["loaded"] == 1
    assert jax.tree.structure(second) == jax.tree.structure(first)
    assert second.system.lagrangian.fn is system.lagrangian.fn  # the caller's own function
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(second)):
        np.testing.assert_array_equal(a, b)
    # A new initial value is the same program (kept in memory: no lookup, no compile).
    third = _simulate(system, q0=0.7)
    assert dict(saved_programs.statistics) == {"compiled": 1, "saved": 1, "loaded": 1}
    assert not np.array_equal(third.q, first.q)
    # Derived quantities: one program per quantity, saved and loaded the same way.
    energy = first.energy
    np.testing.assert_allclose(energy, energy[0], rtol=1e-9)
    _evaluate._memory.clear()
    np.testing.assert_allclose(third.energy, _energy_by_hand(third), rtol=1e-13)
    np.testing.assert_array_equal(first.energy, energy)
    assert dict(saved_programs.statistics) == {"compiled": 2, "saved": 2, "loaded": 2}


def _energy_by_hand(trajectory):
    q, qd = np.asarray(trajectory.q)[:, 0], np.asarray(trajectory.qd)[:, 0]
    return 0.5 * qd**2 - 9.81 * np.cos(q)


def test_calls_the_fingerprint_cannot_describe_run_as_before(program_cache):
    class MyTsit5(diffrax.Tsit5):  # the user's own class: its code is not fingerprinted
        pass

    @jax.custom_jvp
    def softened(x):  # a custom rule: the jaxpr names it by address
        return jnp.cos(x)

    softened.defjvp(lambda p, t: (jnp.cos(p[0]), -jnp.sin(p[0]) * t[0]))
    system = _pendulum()
    reference = _simulate(system)
    saved_programs.statistics.clear()
    custom = _simulate(system, solver=MyTsit5())
    rule = _simulate(jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2
                               + args["g"] * softened(q[0])))
    assert dict(saved_programs.statistics) == {"uncacheable": 2}
    np.testing.assert_array_equal(custom.q, reference.q)
    np.testing.assert_allclose(rule.q, reference.q, rtol=1e-12, atol=1e-12)


def test_jit_vmap_and_grad_with_programs_saved(program_cache):
    system = _pendulum()
    reference = _simulate(system).q
    jitted = jax.jit(lambda q0: _simulate(system, q0=q0).q)(0.5)
    batched = jax.vmap(lambda q0: _simulate(system, q0=q0).q)(jnp.array([0.5, 0.6]))
    np.testing.assert_allclose(jitted, reference, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(batched[0], reference, rtol=1e-12, atol=1e-14)

    def loss(g):
        return jnp.sum(jl.simulate(system, jnp.array([0.5]), jnp.zeros(1),
                                   jnp.linspace(0.0, 1.0, 6), args={"g": g}).q ** 2)

    grad = jax.grad(loss)(9.81)
    assert saved_programs.statistics["saved"] == 2  # the solve and the tangent solve
    _solve_with_tangents._memory.clear()
    assert jax.grad(loss)(9.81) == grad  # loaded: the same executable
    assert saved_programs.statistics["loaded"] == 1
    step = 1e-5
    finite = (loss(9.81 + step) - loss(9.81 - step)) / (2 * step)
    np.testing.assert_allclose(grad, finite, rtol=1e-6)
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(9.81), grad, rtol=1e-12)


def _solve_arguments(system, q0):
    """The arguments simulate gives _solve for a pendulum (the fingerprinted call)."""
    return (system, q0, jnp.zeros_like(q0), np.asarray(0.0), np.asarray(1.0), None,
            {"g": jnp.asarray(9.81)}, diffrax.Tsit5(),
            diffrax.PIDController(rtol=1e-10, atol=1e-10),
            diffrax.SaveAt(ts=jnp.linspace(0.0, 1.0, 6)), 2**16, diffrax.ForwardMode(), None,
            diffrax.NoProgressMeter(), None, None, False, 1e-8, True)


def _key(args):
    return _solve._fingerprint(args)[0]


@settings(max_examples=25, deadline=None)
@given(st.floats(0.1, 10.0), st.floats(0.1, 10.0), st.floats(-1.0, 1.0))
def test_fingerprint_follows_constants_not_input_values(a, b, q0):
    same_a = _key(_solve_arguments(_pendulum(a), jnp.array([q0])))
    assert same_a == _key(_solve_arguments(_pendulum(a), jnp.array([0.3])))  # values: inputs
    assert (same_a == _key(_solve_arguments(_pendulum(b), jnp.array([q0])))) == (a == b)


def test_fingerprint_follows_shapes_options_and_closed_over_arrays():
    system = _pendulum()
    base = _solve_arguments(system, jnp.array([0.5]))
    keys = {_key(base)}
    weights = np.array([1.0, 2.0])
    heavy = jl.System(lambda q, qd, args: 0.5 * weights[0] * qd[0] ** 2 + jnp.cos(q[0]))
    variants = [
        eqx.tree_at(lambda a: a[7], base, diffrax.Dopri5()),  # another solver
        eqx.tree_at(lambda a: a[8], base, diffrax.PIDController(rtol=1e-8, atol=1e-10)),
        eqx.tree_at(lambda a: a[10], base, 1000),  # max_steps
        eqx.tree_at(lambda a: a[9], base, diffrax.SaveAt(ts=jnp.linspace(0.0, 1.0, 7))),
        _solve_arguments(heavy, jnp.array([0.5])),
    ]
    for variant in variants:
        keys.add(_key(variant))
    weights[0] = 3.0  # the closed-over array's values are part of the program
    keys.add(_key(_solve_arguments(heavy, jnp.array([0.5]))))
    assert len(keys) == len(variants) + 2


def test_an_unreadable_file_is_replaced_and_the_switch_turns_saving_off(program_cache,
                                                                         monkeypatch):
    system = _pendulum()
    reference = _simulate(system)
    (name,) = os.listdir(program_cache)
    (program_cache / name).write_bytes(b"not a program")
    _solve._memory.clear()
    again = _simulate(system)
    assert dict(saved_programs.statistics) == {"compiled": 2, "saved": 2}
    np.testing.assert_array_equal(again.q, reference.q)
    assert (program_cache / name).stat().st_size > 1000  # replaced by the program
    monkeypatch.setenv("JAXLAG_PROGRAM_CACHE", "0")
    saved_programs.statistics.clear()
    _simulate(_pendulum(2.0))
    assert dict(saved_programs.statistics) == {}
    assert len(os.listdir(program_cache)) == 1


def test_event_runs_are_saved_with_their_conditions_fingerprinted(program_cache):
    solve_segments = sys.modules["jaxlag.events"].solve_segments
    solve_segments._memory.clear()
    system = _pendulum()

    def run(level):  # a new condition function each time: found by its jaxpr, not its identity
        return jl.simulate(system, jnp.array([0.5]), jnp.zeros(1), jnp.linspace(0.0, 2.0, 11),
                           args={"g": 9.81}, events=jl.Event(lambda q, qd: q[0] - level))

    first, again, other = run(0.0), run(0.0), run(0.1)
    assert dict(saved_programs.statistics) == {"compiled": 2, "saved": 2, "loaded": 1}
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
    assert jax.tree.structure(first) == jax.tree.structure(again)
    # The pendulum released at q = 0.5 from rest crosses q = 0.1 before q = 0 (a quarter period).
    assert 0 < float(other.events.time[0]) < float(first.events.time[0])
    solve_segments._memory.clear()


def test_disable_jit_and_debug_nans_bypass_saved_programs(program_cache):
    system = _pendulum()
    reference = _simulate(system)
    saved_programs.statistics.clear()
    with jax.disable_jit():
        eager = _simulate(system, solver=diffrax.Euler(),
                          stepsize_controller=diffrax.ConstantStepSize(), dt0=0.05)
    with jax.debug_nans(True):
        checked = _simulate(system)
    assert dict(saved_programs.statistics) == {}
    compiled = _simulate(system, solver=diffrax.Euler(),
                         stepsize_controller=diffrax.ConstantStepSize(), dt0=0.05)
    np.testing.assert_allclose(eager.q, compiled.q, rtol=1e-12)  # same steps, op by op
    np.testing.assert_array_equal(checked.q, reference.q)


def test_fit_saves_its_least_squares_program_with_the_observation_fingerprinted(program_cache):
    linearize = sys.modules["jaxlag.fit"]._linearize
    linearize._memory.clear()
    system = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 + args["g"] * jnp.cos(q[0]))
    truth = _simulate(system)  # g = 9.81
    experiment = jl.Experiment(truth.t, truth.q, jnp.array([0.5]), jnp.zeros(1))

    def fitted(observe):
        return jl.fit(system, {"g": 8.0}, experiment, observe=observe).params["g"]

    saved_programs.statistics.clear()
    first = fitted(lambda q, qd, args: q)
    assert saved_programs.statistics["saved"] >= 1
    before = dict(saved_programs.statistics)
    linearize._memory.clear()
    assert fitted(lambda q, qd, args: q) == first  # a new function, the same jaxpr: loaded
    assert saved_programs.statistics["loaded"] == before.get("loaded", 0) + 1
    np.testing.assert_allclose(first, 9.81, rtol=1e-8)
    # Another observation function (another jaxpr): another program.
    np.testing.assert_allclose(fitted(lambda q, qd, args: 1.0 * q + 0.0 * qd), 9.81, rtol=1e-8)
    assert saved_programs.statistics["compiled"] == before["compiled"] + 1
    linearize._memory.clear()
