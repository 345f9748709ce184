"""The fault catalogue of issue 37 ("Trustworthy results, round 2"), before and after.

Every case of the issue, through the public API, in the modes where it applies (eager, ``jit``,
``vmap``, ``grad``; float64, and float32 for a few contact cases), run against two source trees:
the tree before the fixes (``--before``, e.g. a worktree of 910a34b) and this checkout
(``--after``, default: the ``src`` beside this file). Each group of cases runs in its own
process per tree (``PYTHONPATH`` set to that tree's ``src``), and each cell is guarded, so one
failure, or a process that dies, does not stop the catalogue.

Each cell is a verdict and what the user sees:

- ``ok``: the right number, or an error/warning that names the cause;
- ``wrong (no error)``: a wrong number and no error or warning;
- ``misleading``: an error (or a silent result) that does not name the cause;
- ``crash``: an error from deep inside a dependency;
- ``fails``: a valid input that is refused;
- ``missing``: the API the case needs does not exist in that tree (what its user saw instead);
- ``problem``: a documentation case that is not fixed.

Not a benchmark and not a test (the regression tests live in tests/test_impacts.py,
tests/test_fit_trust.py, tests/test_learned_trust.py, tests/test_control.py, tests/test_friction.py
and tests/test_failures.py). From the repository root::

    python -m benchmarks.fault_catalogue_trust --before ../base_trust/src
    python -m benchmarks.fault_catalogue_trust --tree src --groups ball,fit   # one tree, some groups
"""

import argparse
import json
import math
import os
import re
import resource
import subprocess
import sys
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import jax

# The worker's dtype is chosen before any array is made (the driver needs neither).
jax.config.update("jax_enable_x64", "--float32" not in sys.argv)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

WIDTH = 110
G = 9.81
Thunk = Callable[[], str]
Cell = tuple[str, str, Thunk]  # (case, mode, what the user sees)


# ----------------------------------------------------------------------------- verdicts
def flat(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def clip(text: str, width: int = WIDTH) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 1] + "…"


def message(exc: BaseException) -> str:
    """The library's text: under jit it sits inside a runtime error, after a traceback (whose
    source lines must not count as the message) and before equinox's advice on filter_jit."""
    text = flat(exc)
    marker = "jaxlag:"
    if marker in text:
        text = "…" + text[text.index(marker) :].split(" -------------------- ")[0]
    return text


def describe(exc: BaseException, *patterns: str) -> str:
    """The type and the first words of the message; where the first of ``patterns`` that the
    message holds lies beyond them, the words around it too."""
    text = message(exc)
    shown = clip(text)
    for pattern in patterns:
        found = re.search(pattern, text)
        if found is None:
            continue
        if found.start() > WIDTH - 30:
            start = min(text.find(" ", max(found.start() - 40, 0)) + 1, found.start())  # a word's start
            shown = clip(text[:48], 48) + " … " + clip(text[start : found.end() + 60], 110)
        break
    return f"{type(exc).__name__}: {shown}"


def refusal(run: Callable[[], str], cause: str, *, otherwise: str = "misleading", blame: str = "") -> Thunk:
    """A case whose right outcome is an error that names ``cause`` (a regex on the library's
    message); ``run`` returns what came back when nothing was raised; ``blame``: what a misleading
    message says instead (shown)."""

    def thunk() -> str:
        try:
            shown = run()
        except Exception as exc:  # noqa: BLE001 - the catalogue reports every failure
            if re.search(cause, message(exc)):
                return f"ok: {describe(exc, cause)}"
            return f"{otherwise}: {describe(exc, *([blame] if blame else []))}"
        return f"wrong (no error): {shown}"

    return thunk


def valid(run: Callable[[], tuple[bool, str]]) -> Thunk:
    """A valid input: ``run`` returns (whether the result is right, what it shows)."""

    def thunk() -> str:
        try:
            right, shown = run()
        except AttributeError as exc:  # an API of the other tree
            return f"missing: {describe(exc)}"
        except Exception as exc:  # noqa: BLE001
            return f"fails: {describe(exc)}"
        return f"{'ok' if right else 'wrong (no error)'}: {shown}"

    return thunk


def diagnosed(run: Callable[[], str], cause: str, *, silent: str = "misleading (no warning)") -> Thunk:
    """A case whose right outcome is a warning or an error naming ``cause``."""

    def thunk() -> str:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                shown = run()
            except Exception as exc:  # noqa: BLE001
                if re.search(cause, message(exc)):
                    return f"ok: {describe(exc, cause)}"
                return f"misleading: {describe(exc)}"
        named = [w for w in caught if re.search(cause, " ".join(str(w.message).split()))]
        if named:
            return f"ok, {named[0].category.__name__}: {clip(str(named[0].message))}"
        return f"{silent}: {shown}"

    return thunk


def ready(x: Any) -> Any:
    return jax.block_until_ready(x)


def log_of(traj: Any) -> Any:
    """``traj.events`` (a run with events has one)."""
    assert traj.events is not None
    return traj.events


# ----------------------------------------------------------------------------- closed forms
def ball_height(t: float, h: float, e: float) -> float:
    """A ball dropped from h onto z = 0 with restitution e (no plastic end: t well before it)."""
    tk = math.sqrt(2 * h / G)
    if t <= tk:
        return h - 0.5 * G * t * t
    w = e * math.sqrt(2 * G * h)
    while t > tk + 2 * w / G:
        tk, w = tk + 2 * w / G, e * w
    s = t - tk
    return w * s - 0.5 * G * s * s


def _ball_lagrangian(q, qd):
    return 0.5 * qd[0] ** 2 - G * q[0]


def _floor(q):
    return q[:1]


def ball(e):
    import jaxlag as jl

    return jl.System(_ball_lagrangian, _floor, unilateral=jl.Unilateral(0, restitution=e))


# ----------------------------------------------------------------------------- 1 ball on a floor
def group_ball() -> Iterator[Cell]:
    """Restitution out of range, its gradient, impact kinds and times, the throw from the floor:
    one ball on z ≥ 0, the restitution an array leaf (one program per mode)."""
    import jaxlag as jl

    ts = jnp.linspace(0.0, 3.0, 31)
    events = jl.Events(max_segments=32)

    def run(e, q0=1.0, qd0=0.0):
        return jl.simulate(ball(e), jnp.reshape(q0, (1,)), jnp.reshape(qd0, (1,)), ts, events=events)

    def max_height(e):  # the highest point after the first landing (at 0.45 s)
        return jnp.max(run(e).q[5:, 0])

    def second_impact(e):  # the second entry of the log: the second landing of a ball dropped from 1 m
        return log_of(run(e)).time[1]

    for value, name in ((1.5, "1.5"), (-0.5, "−0.5"), (math.nan, "NaN")):
        case = f"04 restitution e = {name}, traced (ball dropped from 1 m)"
        e = jnp.asarray(value)

        def shown(z, value=value):
            rise = "above its 1 m drop" if z > 1.0 + 1e-9 else "stuck to the floor" if z < 1e-9 else ""
            return f"highest point after the first landing z = {z:.3g} m, {rise} (e = {value})"

        yield case, "eager (e a number)", refusal(lambda value=value: f"built: {ball(value)}", "restitution")
        yield case, "jit", refusal(lambda e=e: shown(float(ready(jax.jit(max_height)(e)))), "restitution")
        yield (
            case,
            "vmap (e = [0.5, bad])",
            refusal(
                lambda e=e: shown(float(ready(jax.vmap(max_height)(jnp.stack([jnp.asarray(0.5), e])))[1])),
                "restitution",
            ),
        )
        yield (
            case,
            "grad",
            refusal(lambda e=e: f"d(max z)/de = {float(ready(jax.grad(max_height)(e))):.4g}", "restitution"),
        )

    case = "04 ∂(2nd bounce time)/∂e at e = 1.2"
    bad = jnp.asarray(1.2)
    yield case, "grad", refusal(lambda: f"{float(ready(jax.grad(second_impact)(bad))):.4g}", "restitution")
    yield (
        case,
        "jit(grad)",
        refusal(lambda: f"{float(ready(jax.jit(jax.grad(second_impact))(bad))):.4g}", "restitution"),
    )
    yield (
        case,
        "vmap(grad) (e = [0.8, 1.2])",
        refusal(
            lambda: f"{float(ready(jax.vmap(jax.grad(second_impact))(jnp.array([0.8, 1.2])))[1]):.4g}",
            "restitution",
        ),
    )

    case = "14 ball thrown up from the floor (z = 0, ż = 3 m/s, e = 0.5)"
    w, e_throw = 3.0, 0.5
    expected = 2 * w / G * np.array([1.0, 1.0 + e_throw])

    def landings(e):
        return log_of(run(e, 0.0, w)).time[:2]

    def thrown(times) -> tuple[bool, str]:
        times = np.asarray(times)
        right = bool(np.all(np.abs(times - expected) < 1e-9))
        return (
            right,
            f"landings {times[0]:.6f}, {times[1]:.6f} s "
            f"(2w/g, 2w/g(1+e): {expected[0]:.6f}, {expected[1]:.6f})",
        )

    e05 = jnp.asarray(e_throw)
    yield case, "eager", valid(lambda: thrown(ready(landings(e05))))
    yield case, "jit", valid(lambda: thrown(ready(jax.jit(landings)(e05))))
    yield case, "vmap", valid(lambda: thrown(ready(jax.vmap(landings)(e05[None]))[0]))

    case = "17 impact kinds: traj.events.kinds() (e = 0.5)"

    def kinds() -> tuple[bool, str]:
        listed = log_of(run(jnp.asarray(0.5))).kinds()[:3]
        return "impact" in listed, f"kinds()[:3] = {listed}"

    yield case, "eager", valid(kinds)

    def is_impact(e):
        return log_of(run(e)).kind[:3] == jl.EventKind.IMPACT

    def compiled_kinds() -> tuple[bool, str]:
        flags = np.asarray(ready(jax.jit(is_impact)(jnp.asarray(0.5))))
        return bool(flags.all()), f"events.kind[:3] == jl.EventKind.IMPACT: {flags.tolist()}"

    yield case, "jit", valid(compiled_kinds)

    case = "17 impact times under grad: ∂ impact_times(2)[1] / ∂e at e = 0.8"
    slope = 2 * math.sqrt(2.0 / G)  # t₂ = √(2h/g)(1 + 2e)

    def impact_time(e):
        return log_of(run(e)).impact_times(2)[1]

    def derivative(value) -> tuple[bool, str]:
        value = float(value)
        return abs(value - slope) < 1e-8, f"{value:.10f} (closed form 2√(2h/g) = {slope:.10f})"

    e08 = jnp.asarray(0.8)
    yield case, "grad", valid(lambda: derivative(ready(jax.grad(impact_time)(e08))))
    yield case, "jit(grad)", valid(lambda: derivative(ready(jax.jit(jax.grad(impact_time))(e08))))
    yield case, "vmap(grad)", valid(lambda: derivative(ready(jax.vmap(jax.grad(impact_time))(e08[None]))[0]))


# ----------------------------------------------------------------------------- 2, 8 Zeno
def group_zeno() -> Iterator[Cell]:
    import jaxlag as jl

    case = "02 ball e = 0.9 from 1 m, saved on ts that end at 1000 s"
    ts = jnp.array([0.0, 0.5, 1.0, 1.5, 2.0, 1000.0])
    events = jl.Events(max_segments=128)
    closed = np.array([ball_height(t, 1.0, 0.9) for t in (1.0, 1.5)])

    def heights(e):
        return jl.simulate(ball(e), jnp.ones(1), jnp.zeros(1), ts, events=events).q[2:4, 0]

    def compare(z) -> tuple[bool, str]:
        z = np.asarray(z)
        right = bool(np.all(np.abs(z - closed) < 1e-8))
        return (
            right,
            f"z(1 s), z(1.5 s) = {z[0]:.4f}, {z[1]:.4f} m (closed form {closed[0]:.4f}, {closed[1]:.4f})",
        )

    e = jnp.asarray(0.9)
    yield case, "eager", valid(lambda: compare(ready(heights(e))))
    yield case, "jit", valid(lambda: compare(ready(jax.jit(heights)(e))))
    yield case, "vmap", valid(lambda: compare(ready(jax.vmap(heights)(e[None]))[0]))

    case = "08 Zeno: e = 0.999, zeno_time = 1e-9, max_segments = 64, ts = [0, 2000]"
    e_zeno, zeno = 0.999, 1e-9
    needed = (
        math.ceil(math.log(zeno / (2 * math.sqrt(2.0 / G))) / math.log(e_zeno)) + 1
    )  # impacts and the end
    long_ts = jnp.array([0.0, 2000.0])
    advised: dict[str, int] = {}

    def simulate(segments: int, throw: bool = True):
        return jl.simulate(
            ball(jnp.asarray(e_zeno)),
            jnp.ones(1),
            jnp.zeros(1),
            long_ts,
            events=jl.Events(max_segments=segments, zeno_time=zeno),
            throw=throw,
        )

    def advice(exc: BaseException) -> str:
        text = message(exc)
        found = re.findall(r"max_segments=([\d,]+)", text)
        if not found:
            return f"misleading: {describe(exc)}"
        advised["n"] = int(found[-1].replace(",", ""))
        named = "zeno_time" in text
        label = "ok" if advised["n"] >= needed and named else "misleading"
        return (
            f"{label}: {type(exc).__name__}: advises max_segments={advised['n']} (the run needs {needed:,}); "
            f"zeno_time {'named' if named else 'not named'}"
        )

    def eager_advice() -> str:
        try:
            simulate(64)
        except Exception as exc:  # noqa: BLE001
            return advice(exc)
        return "wrong (no error): ran with 64 segments"

    def compiled_advice() -> str:
        try:
            traj = jax.jit(lambda: simulate(64, throw=False))()
            traj.raise_if_failed()
        except Exception as exc:  # noqa: BLE001
            return advice(exc)
        return "wrong (no error): ran with 64 segments"

    def rerun() -> tuple[bool, str]:
        if "n" not in advised:
            raise RuntimeError("no advice to follow")
        traj = simulate(advised["n"])
        return True, f"ran to 2000 s with max_segments={advised['n']}: {int(log_of(traj).count):,} segments"

    yield case, "eager", eager_advice
    yield case, "eager, with the advised max_segments", valid(rerun)
    yield case, "jit, throw=False → raise_if_failed()", compiled_advice


# ----------------------------------------------------------------------------- 9 long elastic run
def group_elastic() -> Iterator[Cell]:
    import jaxlag as jl

    case = "09 elastic ball (e = 1) from 1 m over 400 s: 443 impacts"
    events = jl.Events(max_segments=448)
    ts = jnp.array([0.0, 400.0])
    t1 = math.sqrt(2.0 / G)

    def log(h):
        traj = jl.simulate(ball(jnp.asarray(1.0)), jnp.reshape(h, (1,)), jnp.zeros(1), ts, events=events)
        return log_of(traj).time, log_of(traj).count

    def check(times, count) -> tuple[bool, str]:
        times = np.asarray(times)[: int(count)]
        times = times[times < 400.0 - 1e-6]  # the impacts (the last entry is the end)
        k = np.arange(len(times))
        error = float(np.max(np.abs(times - t1 * (2 * k + 1))))
        right = len(times) == 443 and error < 1e-8
        return right, f"{len(times)} impacts, t_k − √(2h/g)(2k+1) at most {error:.1e} s"

    h = jnp.asarray(1.0)
    yield case, "eager", valid(lambda: check(*ready(log(h))))
    yield case, "jit", valid(lambda: check(*ready(jax.jit(log)(h))))

    def mapped() -> tuple[bool, str]:
        times, count = ready(jax.vmap(log)(h[None]))
        return check(times[0], count[0])

    yield case, "vmap", valid(mapped)


# ----------------------------------------------------------------------------- 5 friction
def group_friction() -> Iterator[Cell]:
    import jaxlag as jl

    mass, theta = 2.0, math.radians(30.0)
    ts = jnp.linspace(0.0, 0.2, 5)
    slope = {"theta": jnp.asarray(theta)}

    def lagrangian(q, qd):
        return 0.5 * mass * (qd @ qd) - mass * G * q[1]

    def surface(q, args):
        th = args["theta"]
        return jnp.stack([-jnp.sin(th) * q[0] + jnp.cos(th) * q[1]])

    def along(q, args):
        th = args["theta"]
        return jnp.cos(th) * q[0] + jnp.sin(th) * q[1]

    def system(mu):
        return jl.System(lagrangian, surface, unilateral=0, friction=jl.Coulomb(0, along, mu))

    def slid(mu):  # released at rest on the 30° ramp: τ(0.2 s)
        traj = jl.simulate(
            system(mu), jnp.zeros(2), jnp.zeros(2), ts, args=slope, events=jl.Events(max_segments=4)
        )
        return along(traj.q[-1], slope)

    t = 0.2
    free = -0.5 * G * math.sin(theta) * t**2

    def shown(tau):
        tau = float(tau)
        how = "faster than frictionless" if tau < free - 1e-9 else "as far as or less than frictionless"
        return f"τ(0.2 s) = {tau:.4f} m, {how} ({free:.4f} m): friction drives the slide"

    for value, name in ((-0.3, "−0.3"), (math.nan, "NaN")):
        case = f"05 friction μ = {name}, traced (block released on a 30° ramp)"
        mu = jnp.asarray(value)
        cause = r"friction coefficient|\bmu\b"
        yield case, "eager (μ a number)", refusal(lambda value=value: f"built: {system(value)}", cause)
        yield case, "jit", refusal(lambda mu=mu: shown(ready(jax.jit(slid)(mu))), cause)
        yield (
            case,
            "vmap (μ = [0.3, bad])",
            refusal(lambda mu=mu: shown(ready(jax.vmap(slid)(jnp.stack([jnp.asarray(0.3), mu])))[1]), cause),
        )
        yield case, "grad", refusal(lambda mu=mu: f"dτ/dμ = {float(ready(jax.grad(slid)(mu))):.4g}", cause)


# ----------------------------------------------------------------------------- 6 control laws
M_P, L_P = 2.0, 0.5


def _pendulum(q, qd):
    return 0.5 * M_P * L_P**2 * qd[0] ** 2 + M_P * G * L_P * jnp.cos(q[0])


def _stacked(q, qd, u):  # Q_u = (u,) for a scalar u; a u of shape (2,) makes it (1, 2)
    return jnp.stack([u])


def _two_inputs(q, qd):
    return jnp.zeros(2)


def _nan_after_half_a_second(q, qd, t):
    return jnp.where(t > 0.5, jnp.nan, -5.0 * q[0])


def _in_mode(fn: Callable, x, mode: str):
    if mode == "eager":
        return ready(fn(x))
    if mode == "jit":
        return ready(jax.jit(fn)(x))
    return ready(jax.vmap(fn)(x[None]))


def group_control() -> Iterator[Cell]:
    import jaxlag as jl

    plant = jl.System(_pendulum, actuation=_stacked)
    theta0 = jnp.array([0.3])

    def wrong_shape(x):
        return jl.simulate(plant.with_control(_two_inputs), x, jnp.zeros(1), jnp.array([0.0, 0.1])).q

    case = "06 control law returning u of the wrong shape"
    for mode in ("eager", "jit", "vmap"):
        yield (
            case,
            mode,
            refusal(lambda mode=mode: f"ran: {_in_mode(wrong_shape, theta0, mode).shape}", "control law"),
        )

    controlled = plant.with_control(_nan_after_half_a_second)
    ts = jnp.array([0.0, 1.0])

    def nan_law(x):
        return jl.simulate(controlled, x, jnp.zeros(1), ts).q

    case = "06 control law returning NaN after 0.5 s"
    blame = r"force or dissipation"
    yield (
        case,
        "eager",
        refusal(lambda: f"ran: {_in_mode(nan_law, theta0, 'eager')}", "control law", blame=blame),
    )
    # Compiled: the static message says what became non-finite; it must not blame a force or
    # dissipation the system does not have.
    honest = r"^(?!.*force or dissipation).*non-finite"
    yield case, "jit", refusal(lambda: f"ran: {_in_mode(nan_law, theta0, 'jit')}", honest)
    yield case, "vmap", refusal(lambda: f"ran: {_in_mode(nan_law, theta0, 'vmap')}", honest)

    def kept() -> str:
        traj = jax.jit(lambda x: jl.simulate(controlled, x, jnp.zeros(1), ts, throw=False))(theta0)
        traj.raise_if_failed()
        return "raise_if_failed() raised nothing"

    yield case, "jit, throw=False → raise_if_failed()", refusal(kept, "control law", blame=blame)


# ----------------------------------------------------------------------------- 7 resets
def _falling(q, qd):
    return 0.5 * qd[0] ** 2 - G * q[0]


def bad_bounce(q, qd):  # q̇ < 0 at the floor: √q̇ is NaN
    return q, jnp.sqrt(qd)


def reset_cells(modes: tuple[str, ...]) -> Iterator[Cell]:
    import jaxlag as jl

    events = jl.Events(jl.Event(lambda q, qd: q[0], terminal=False, direction=False, reset=bad_bounce))
    ts = jnp.linspace(0.0, 1.0, 11)

    def run(h):
        return jl.simulate(jl.System(_falling), h, jnp.zeros(1), ts, events=events).q

    case = "07 event reset returning NaN (ball dropped from 1 m, q̇⁺ = √q̇)"
    for mode in modes:
        plain = mode.removeprefix("float32 ")
        yield (
            case,
            mode,
            refusal(
                lambda plain=plain: (
                    f"ran: q(1 s) = {np.asarray(_in_mode(run, jnp.array([1.0]), plain))[..., -1, :]}"
                ),
                "reset",
            ),
        )


def group_reset() -> Iterator[Cell]:
    yield from reset_cells(("eager", "jit", "vmap"))


# ----------------------------------------------------------------------------- fit
def group_fit() -> Iterator[Cell]:
    import jaxlag as jl

    ts = jnp.linspace(0.0, 2.0, 21)
    q0, qd0 = jnp.array([0.9]), jnp.array([0.0])
    truth = {"g": 9.81, "l": 0.8, "m": 1.0}

    def pendulum(q, qd, args):
        m, g, l = args["m"], args["g"], args["l"]
        return 0.5 * m * l**2 * qd[0] ** 2 + m * g * l * jnp.cos(q[0])

    def bob(q, qd, args):
        return args["l"] * jnp.array([jnp.sin(q[0]), -jnp.cos(q[0])])

    system = jl.System(pendulum)
    theta = np.asarray(jl.simulate(system, q0, qd0, ts, args=truth).q)
    rng = np.random.default_rng(0)
    clean = np.asarray(jax.vmap(lambda q: bob(q, None, truth))(jnp.asarray(theta)))
    noisy = clean + 0.01 * rng.standard_normal(clean.shape)

    case = "03 jl.fit with jl.MultiStart({'g': np.zeros(0), 'l': np.zeros(0)})"

    def empty() -> str:
        starts = jl.MultiStart({"g": np.zeros(0), "l": np.zeros(0)})
        result = jl.fit(system, starts, jl.Experiment(ts, theta, q0, qd0), args={"m": 1.0})
        return f"fitted: {result.params}"

    yield case, "eager", refusal(empty, r"zero starting points|no starting point", otherwise="crash")

    case = "11 jl.Bounded(15.0, 5.0) (bounds reversed), start g = 10"

    def reversed_fit() -> str:
        result = jl.fit(
            system,
            {"g": 10.0},
            jl.Experiment(ts, theta, q0, qd0),
            args={"m": 1.0, "l": 0.8},
            transforms={"g": jl.Bounded(15.0, 5.0)},
        )
        return f"fitted g = {float(result.params['g']):.4g}"

    reversed_bounds = r"lower bound must be below|did you mean Bounded\(5.0, 15.0\)"
    yield case, "eager", refusal(reversed_fit, reversed_bounds)

    def reversed_jit() -> str:
        value = float(ready(jax.jit(lambda u: jl.Bounded(15.0, 5.0).to_physical(u))(0.0)))
        return f"Bounded(15.0, 5.0).to_physical(0.0) = {value:.4g} (the interval is empty)"

    yield case, "jit (to_physical)", refusal(reversed_jit, reversed_bounds)

    case = "12 jl.fit whose data hold one outlier of 1e6"
    spoiled = noisy.copy()
    spoiled[7, 0] = 1e6

    def outlier() -> str:
        result = jl.fit(
            system,
            {"g": 11.0, "l": 0.7},
            jl.Experiment(ts, spoiled, q0, qd0),
            observe=bob,
            args={"m": 1.0},
            transforms={"g": jl.Positive(), "l": jl.Positive()},
        )
        return f"g = {float(result.params['g']):.4g}, l = {float(result.params['l']):.4g}, no warning"

    yield case, "eager", diagnosed(outlier, r"outlier", silent="misleading (no warning)")

    case = "13 jl.fit from a poor start (g = l = 2), no noise_std (data noise 0.01)"

    def poor_start() -> str:
        result = jl.fit(
            system, {"g": 2.0, "l": 2.0}, jl.Experiment(ts, noisy, q0, qd0), observe=bob, args={"m": 1.0}
        )
        return (
            f"converged = {bool(result.converged)}, residual std {float(result.residual_std):.2f}, no warning"
        )

    yield case, "eager", diagnosed(poor_start, r"local minimum|not noise")

    case = "15 θ-only pendulum fit: what is determined (noise 0.01, noise_std given)"
    angle = theta + 0.01 * np.random.default_rng(5).standard_normal(theta.shape)  # Σ z² = 18.7
    fitted: dict[str, Any] = {}

    def identifiable() -> tuple[bool, str]:
        fitted["result"] = result = jl.fit(
            system,
            {"g": 11.0, "l": 0.7},
            jl.Experiment(ts, angle, q0, qd0),
            args={"m": 1.0},
            noise_std=0.01,
        )
        covariance = np.array2string(np.asarray(result.covariance), precision=3, separator=", ").replace(
            "\n", ""
        )
        try:
            combinations = result.identifiable
        except AttributeError:
            return False, f"FitResult has no identifiable (AttributeError); the covariance is {covariance}"
        if not combinations:
            return False, f"no combination reported; the covariance is {covariance}"
        shown = "; ".join(f"{c.name} = {c.value:.5g} ± {c.standard_error:.2g}" for c in combinations)
        return True, f"{shown} (g/l = {9.81 / 0.8:.5g})"

    def identifiable_verdict() -> str:
        try:
            right, shown = identifiable()
        except Exception as exc:  # noqa: BLE001
            return f"fails: {describe(exc)}"
        return f"{'ok' if right else 'missing'}: {shown}"

    yield case, "eager", identifiable_verdict

    case = "16 print(FitResult) (the θ-only fit)"

    def printed() -> str:
        if "result" not in fitted:
            raise RuntimeError("the θ-only fit did not run")
        text = str(fitted["result"])
        if "f64[" in text:
            return f"misleading: {clip(text, 90)}"
        lines = [line.strip() for line in text.splitlines() if line.strip()]
        return "ok: " + clip(" / ".join(lines[:4]), 160)

    yield case, "eager", printed


# ----------------------------------------------------------------------------- learned models
def group_learned() -> Iterator[Cell]:
    import equinox as eqx
    import optax

    import jaxlag as jl
    from jaxlag import learned as jll

    key = jax.random.PRNGKey(0)
    truth = jl.systems.double_pendulum()
    kq, kv = jax.random.split(jax.random.PRNGKey(1))
    q = jax.random.uniform(kq, (64, 2), minval=-1.0, maxval=1.0)
    qd = jax.random.uniform(kv, (64, 2), minval=-1.0, maxval=1.0)
    qdd = jax.vmap(lambda a, b: jll.accelerations(truth, a, b))(q, qd)

    def trained(result, rows: int = 64) -> str:
        leaves = [np.asarray(x) for x in jax.tree.leaves(eqx.filter(result.model, eqx.is_inexact_array))]
        bad = sum(int(np.sum(~np.isfinite(x))) for x in leaves)
        total = sum(x.size for x in leaves)
        failed = np.asarray(result.failed).reshape(-1)
        return (
            f"train returned a model with {bad}/{total} weights non-finite, "
            f"last train loss {float(np.asarray(result.train_loss)[-1]):.3g}, "
            f"failed {int(failed[-1])} of {rows} rows"
        )

    def model():
        return jll.DeLaN(2, 16, 2, key=key)

    for field, rows_name in (("qdd", "targets (qdd)"), ("q", "inputs (q)")):
        case = f"01 jll.train on StateData with 2 NaN rows in the {rows_name}"
        arrays = {"q": q, "qd": qd, "qdd": qdd}

        def built(field=field) -> str:
            broken = dict(arrays, **{field: arrays[field].at[jnp.array([3, 10])].set(jnp.nan)})
            data = jll.StateData(broken["q"], broken["qd"], broken["qdd"])
            return trained(jll.train(model(), jll.AccelerationLoss(), data, steps=3))

        def bypassed(field=field) -> str:
            data = jll.StateData(q, qd, qdd)
            data = eqx.tree_at(
                lambda d: getattr(d, field), data, arrays[field].at[jnp.array([3, 10])].set(jnp.nan)
            )
            return trained(jll.train(model(), jll.AccelerationLoss(), data, steps=3))

        yield case, "eager, StateData(...)", refusal(built, r"not finite")
        yield case, "eager, data built by eqx.tree_at", refusal(bypassed, r"not finite")

    good = jll.StateData(q, qd, qdd)

    case = "10 jll.train on 0 rows"

    def no_rows() -> str:
        empty = jll.StateData(q[:0], qd[:0], qdd[:0])
        return trained(jll.train(model(), jll.AccelerationLoss(), empty, steps=3), rows=0)

    yield case, "eager", refusal(no_rows, r"no rows")

    case = "10 jll.train with optax.adam(inf)"

    def infinite_rate() -> str:
        return trained(
            jll.train(model(), jll.AccelerationLoss(), good, optimizer=optax.adam(jnp.inf), steps=3)
        )

    yield case, "eager", refusal(infinite_rate, r"learning rate|update is not")

    case = "10 jll.TrajectoryData with decreasing ts (one of 3 rows), then train"

    def decreasing() -> str:
        ts = jnp.linspace(0.0, 1.0, 11)
        q0 = jnp.array([[0.5], [1.0], [-0.7]])
        oscillator = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 0.5 * q[0] ** 2)
        truth_traj = jl.simulate_batch(oscillator, q0, 0.0 * q0, ts)
        times = jnp.broadcast_to(ts, (3, 11)).at[1].set(ts[::-1])
        data = jll.TrajectoryData(times, truth_traj.q, truth_traj.qd)
        result = jll.train(jll.DeLaN(1, 4, 1, key=key), jll.RolloutLoss(), data, steps=2)
        return "accepted; " + trained(result, rows=3)

    yield case, "eager", refusal(decreasing, r"ts must increase|increas")

    case = "10 jll.DeLaN(3, ...) trained on 2-coordinate data"

    def wrong_size() -> str:
        return trained(jll.train(jll.DeLaN(3, 8, 1, key=key), jll.AccelerationLoss(), good, steps=1))

    yield case, "eager", refusal(wrong_size, r"n = 3")

    case = "18 jll.state_data(data, model) (arguments swapped)"

    def swapped() -> str:
        data = jll.TrajectoryData(
            jnp.broadcast_to(jnp.linspace(0.0, 0.2, 3), (1, 3)), jnp.zeros((1, 3, 2)), jnp.zeros((1, 3, 2))
        )
        return f"returned {type(jll.state_data(data, truth)).__name__}"  # pyright: ignore[reportArgumentType]

    yield case, "eager", refusal(swapped, r"swap|first and the TrajectoryData second")

    case = "20 the cookbook's training recipe as a library call: jll.train_recipe"

    def recipe() -> tuple[bool, str]:
        short = jll.Recipe(steps=30, batch_size=32)
        result = jll.train_recipe(model(), good, recipe=short, key=key)
        losses = np.asarray(result.acceleration.train_loss)
        right = bool(np.all(np.isfinite(losses)) and losses[-5:].mean() < losses[:5].mean())
        return right, f"Recipe(steps=30): train loss {losses[:5].mean():.3g} → {losses[-5:].mean():.3g}"

    yield case, "eager", valid(recipe)


# ----------------------------------------------------------------------------- documentation
def group_docs() -> Iterator[Cell]:
    """The documentation cases, read from the tree's files and the public objects' docstrings
    (the API pages are rendered from them)."""
    import importlib
    import inspect

    import jaxlag

    root = Path(jaxlag.__file__).resolve().parents[2]
    private = re.compile(r"jaxlag\._[a-z]\w*")

    def docstring_mentions() -> tuple[int, int]:
        seen: set[int] = set()
        count = pages = 0
        namespaces = ["jaxlag"] + [
            f"jaxlag.{name}"
            for name in (
                "analysis",
                "contact",
                "coordinates",
                "experimental",
                "loads",
                "rotations",
                "systems",
                "learned",
            )
        ]
        for name in namespaces:
            try:
                module = importlib.import_module(name)
            except ImportError:
                continue
            objects = [module] + [getattr(module, a) for a in dir(module) if not a.startswith("_")]
            for obj in objects:
                members = [obj] + ([m for _, m in inspect.getmembers(obj)] if inspect.isclass(obj) else [])
                for member in members:
                    if id(member) in seen:
                        continue
                    seen.add(id(member))
                    doc = getattr(member, "__doc__", None)
                    if isinstance(doc, str):
                        count += len(private.findall(doc))
        for page in sorted((root / "docs" / "api").glob("*.md")):
            found = len(private.findall(page.read_text()))
            count, pages = count + found, pages + (found > 0)
        return count, pages

    def mentions() -> str:
        count, pages = docstring_mentions()
        label = "ok" if count == 0 else "problem"
        return (
            f"{label}: {count} mentions of private jaxlag._… modules in public docstrings and docs/api pages"
        )

    yield "19 API pages point to private modules", "docs", mentions

    def maths() -> str:
        config = (root / "mkdocs.yml").read_text()
        remote = re.findall(r"https://\S*(?:mathjax|katex|cdn)\S*", config, flags=re.IGNORECASE)
        if remote:
            return f"problem: mkdocs.yml loads {remote[0]}"
        return "ok: no remote script or stylesheet in mkdocs.yml (maths rendered at build time)"

    yield "19 maths loads from a CDN", "docs", maths

    def models() -> str:
        page = (root / "docs" / "api" / "systems.md").read_text()
        table = "| model |" in page
        image = root / "docs" / "images" / "systems-simple_pendulum.png"
        width = int.from_bytes(image.read_bytes()[16:20], "big")  # the PNG header's width
        shown = re.findall(r'width="(\d+)"', page)
        layout = f"a table, pictures shown {shown[0]} px wide" if table and shown else "cards"
        label = "problem" if table else "ok"
        return f"{label}: {layout}; picture files {width} px wide"

    yield "19 ready-models page (names broken mid-word, small pictures)", "docs", models


# ----------------------------------------------------------------------------- float32
def group_float32() -> Iterator[Cell]:
    """A few contact cases again in float32 (the worker runs with jax_enable_x64 off)."""
    import jaxlag as jl

    ts = jnp.linspace(0.0, 3.0, 31)
    events = jl.Events(max_segments=32)

    def max_height(e):
        return jnp.max(jl.simulate(ball(e), jnp.ones(1), jnp.zeros(1), ts, events=events).q[5:, 0])

    yield (
        "04 restitution e = 1.5, traced (ball dropped from 1 m)",
        "float32 jit",
        refusal(
            lambda: (
                "highest point after the first landing "
                f"z = {float(ready(jax.jit(max_height)(jnp.asarray(1.5)))):.3g} m"
            ),
            "restitution",
        ),
    )

    def landings(e):
        return log_of(jl.simulate(ball(e), jnp.zeros(1), jnp.array([3.0]), ts, events=events)).time[:2]

    expected = 2 * 3.0 / G * np.array([1.0, 1.5])

    def thrown() -> tuple[bool, str]:
        times = np.asarray(ready(landings(jnp.asarray(0.5))))
        right = bool(np.all(np.abs(times - expected) < 1e-4))
        return (
            right,
            f"landings {times[0]:.5f}, {times[1]:.5f} s (closed form {expected[0]:.5f}, {expected[1]:.5f})",
        )

    yield "14 ball thrown up from the floor (z = 0, ż = 3 m/s, e = 0.5)", "float32 eager", valid(thrown)

    theta = math.radians(30.0)
    slope = {"theta": jnp.asarray(theta, jnp.float32)}

    def lagrangian(q, qd):
        return 0.5 * 2.0 * (qd @ qd) - 2.0 * G * q[1]

    def surface(q, args):
        th = args["theta"]
        return jnp.stack([-jnp.sin(th) * q[0] + jnp.cos(th) * q[1]])

    def along(q, args):
        th = args["theta"]
        return jnp.cos(th) * q[0] + jnp.sin(th) * q[1]

    def slid(mu):
        system = jl.System(lagrangian, surface, unilateral=0, friction=jl.Coulomb(0, along, mu))
        traj = jl.simulate(
            system,
            jnp.zeros(2),
            jnp.zeros(2),
            jnp.linspace(0.0, 0.2, 5),
            args=slope,
            events=jl.Events(max_segments=4),
        )
        return along(traj.q[-1], slope)

    yield (
        "05 friction μ = −0.3, traced (block released on a 30° ramp)",
        "float32 jit",
        refusal(
            lambda: f"τ(0.2 s) = {float(ready(jax.jit(slid)(jnp.asarray(-0.3)))):.4f} m",
            r"friction coefficient|\bmu\b",
        ),
    )
    yield from reset_cells(("float32 jit",))


GROUPS: dict[str, Callable[[], Iterator[Cell]]] = {
    "learned": group_learned,
    "zeno": group_zeno,
    "fit": group_fit,
    "ball": group_ball,
    "friction": group_friction,
    "control": group_control,
    "reset": group_reset,
    "elastic": group_elastic,
    "docs": group_docs,
    "float32": group_float32,
}


def worker(group: str) -> None:
    """Run one group in this process (the tree is the one on PYTHONPATH): a JSON line per cell."""
    import jaxlag

    print(json.dumps({"jaxlag": jaxlag.__file__}), flush=True)
    cells = GROUPS[group]()
    while True:
        try:
            case, mode, thunk = next(cells)
        except StopIteration:
            break
        except Exception as exc:  # noqa: BLE001 - a group that cannot even set up its cases
            print(
                json.dumps({"case": f"({group})", "mode": "setup", "result": f"fails: {describe(exc)}"}),
                flush=True,
            )
            break
        start = time.perf_counter()
        try:
            result = thunk()
        except Exception as exc:  # noqa: BLE001
            result = f"catalogue error: {describe(exc)}"
        seconds = time.perf_counter() - start
        print(json.dumps({"case": case, "mode": mode, "result": result, "seconds": seconds}), flush=True)


# ----------------------------------------------------------------------------- driver
QUOTED = (
    "21 jll.ConstrainedLagrangian against a hand-written one (same data and recipe)",
    "benchmark (quoted, not rerun)",
)


def run_tree(
    src: Path, group: str, timeout: float
) -> tuple[dict[tuple[str, str], str], list[tuple[str, str]]]:
    """One group against one tree: {(case, mode): result} and the order the cells came in."""
    env = dict(os.environ, PYTHONPATH=str(src))
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", group]
    if group == "float32":
        command.append("--float32")
    cells: dict[tuple[str, str], str] = {}
    order: list[tuple[str, str]] = []
    try:
        done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout, check=False)
        stdout, stderr, code = done.stdout, done.stderr, done.returncode
    except subprocess.TimeoutExpired as exc:
        stdout = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        stderr, code = f"timed out after {timeout:.0f} s", None
    for line in stdout.splitlines():
        if not line.startswith("{"):
            continue
        record = json.loads(line)
        if "jaxlag" in record:
            if not Path(record["jaxlag"]).resolve().is_relative_to(src.resolve()):
                raise RuntimeError(f"{group}: imported {record['jaxlag']}, not the tree {src}")
            continue
        key = (record["case"], record["mode"])
        cells[key] = record["result"]
        order.append(key)
        print(
            f"  {src}: {group}: {key[0]} [{key[1]}] {record.get('seconds', 0):.1f} s",
            file=sys.stderr,
            flush=True,
        )
    if code != 0:
        last = [line for line in stderr.strip().splitlines() if line.strip()][-1:] or ["(no output)"]
        cells[(f"({group})", "process")] = f"the worker ended with {code}: {clip(last[0])}"
        order.append((f"({group})", "process"))
    return cells, order


def quoted_comparison(results_learned: Path) -> tuple[str, str]:
    """The hand-written comparison of issue 37 (a 1000-step benchmark, not rerun here): the
    library's constrained model with the old advice (targets divided by σ) and with the recipe's
    loss, against the hand-written model, from benchmarks/RESULTS_learned.md."""
    if not results_learned.exists():
        return "n/a", "n/a"
    rows = {}
    for line in results_learned.read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 4:
            rows[(cells[0], cells[1])] = f"{cells[2]} / {cells[3]}"
    hand = rows.get(("hand-written constrained", "raw"), "?")
    scaled = rows.get(("jll.ConstrainedLagrangian", "scaled"), "?")
    library = rows.get(("jll.ConstrainedLagrangian", "library"), "?")
    return (
        f"quoted: σ-scaled targets (the advice then): θ̈ RMS {scaled} rad/s² "
        f"vs hand-written {hand} (seeds 0/1)",
        f"quoted: jll.Recipe().loss: θ̈ RMS {library} rad/s² vs hand-written {hand} "
        "(benchmarks/RESULTS_learned.md, python -m benchmarks.bench_learned --hand-written)",
    )


def verdict(cell: str) -> str:
    return cell.split(":")[0].split(",")[0].split(" (")[0].strip()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--before", type=Path, help="src of the tree before the fixes (e.g. a worktree of 910a34b)"
    )
    parser.add_argument("--after", type=Path, default=Path(__file__).resolve().parents[1] / "src")
    parser.add_argument("--tree", type=Path, help="run one tree only (a table of case, mode, result)")
    parser.add_argument("--groups", default=",".join(GROUPS), help=f"comma-separated, of {', '.join(GROUPS)}")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per group and tree")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--float32", action="store_true", help=argparse.SUPPRESS)
    options = parser.parse_args()
    if options.worker:
        worker(options.worker)
        return
    groups = [g for g in options.groups.split(",") if g]
    unknown = sorted(set(groups) - set(GROUPS))
    if unknown:
        parser.error(f"unknown groups {unknown}; choose from {', '.join(GROUPS)}")
    trees = [options.tree] if options.tree else [options.before, options.after]
    if any(tree is None for tree in trees):
        parser.error("give --before (and optionally --after), or --tree")
    columns: list[dict[tuple[str, str], str]] = [{} for _ in trees]
    order: list[tuple[str, str]] = []
    wall = [0.0 for _ in trees]
    cpu = [0.0 for _ in trees]
    for group in groups:
        for i, tree in enumerate(trees):
            start, used = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
            cells, seen = run_tree(tree, group, options.timeout)
            now = resource.getrusage(resource.RUSAGE_CHILDREN)
            wall[i] += time.perf_counter() - start
            cpu[i] += now.ru_utime + now.ru_stime - used.ru_utime - used.ru_stime
            columns[i].update(cells)
            order += [key for key in seen if key not in order]
    if "learned" in groups and not options.tree:
        order.append(QUOTED)
        columns[0][QUOTED], columns[1][QUOTED] = quoted_comparison(
            Path(__file__).resolve().parent / "RESULTS_learned.md"
        )
    position = {key: i for i, key in enumerate(order)}
    order.sort(key=lambda key: (key[0][:2], position[key]))  # by the case's number, then as run
    names = ["before", "after"] if not options.tree else [str(options.tree)]
    print("| case | mode | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for case, mode in order:
        shown = [column.get((case, mode), "not run").replace("|", "/") for column in columns]
        print(f"| {case} | {mode} | " + " | ".join(shown) + " |")
    print()
    for name, column in zip(names, columns):
        counts: dict[str, int] = {}
        for key in order:
            if key in column and key != QUOTED:
                label = verdict(column[key])
                counts[label] = counts.get(label, 0) + 1
        summary = ", ".join(f"{label} {count}" for label, count in sorted(counts.items()))
        print(f"- {name}: {summary} (cells)")
    for name, tree, seconds, busy in zip(names, trees, wall, cpu):
        print(f"- {name} ({tree}): {seconds:.0f} s wall, {busy:.0f} s CPU")


if __name__ == "__main__":
    main()
