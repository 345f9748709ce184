"""The fault catalogue of issue 16: bad input through the public API in eager, jit and vmap modes.

Prints a markdown table (case × mode → exception type and the first words of its message, or
"ok"). Not a benchmark and not a test (the regression tests live in tests/test_errors.py); run it
to see what a user sees:  python -m benchmarks.fault_catalogue
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

import jaxlag as jl  # noqa: E402

TS = jnp.linspace(0.0, 1.0, 11)


def pendulum_free():
    return jl.System(lambda q, qd: 0.5 * qd[0] ** 2 + 9.81 * jnp.cos(q[0]))


def cartesian_pendulum():
    def L(q, qd, args):
        return 0.5 * (qd @ qd) - args["g"] * q[1]

    def rod(q, args):
        return jnp.array([q @ q - args["l"] ** 2])

    return jl.System(L, holonomic=rod)


def case_event_unconstrained(mode):
    p = pendulum_free()
    ev = [jl.Event(lambda q, qd: q[0])]
    # A terminal event: the saves after it hold inf (diffrax's convention); the event time is
    # θ(t) = 0 of a pendulum released at 0.3 rad: a quarter period, ≈ 0.504 s.
    run = lambda q0: jl.simulate(p, q0, jnp.zeros(1), TS, events=ev).events.time[..., 0]  # noqa: E731
    return _mode(run, jnp.array([0.3]), mode)


def case_nan_args(mode):
    s = cartesian_pendulum()
    run = lambda g: (
        jl.simulate(
            s,
            jnp.array([1.0, 0.0]),
            jnp.zeros(2),
            TS,  # noqa: E731
            args={"g": g, "l": 1.0},
        ).q
    )
    return _mode(run, jnp.array(jnp.nan), mode)


def case_nan_midrun(mode):
    # V = |q|^1.5 written as q**1.5: NaN once q < 0
    s = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - q[0] ** 1.5)
    run = lambda q0: jl.simulate(s, q0, jnp.array([-3.0]), TS).q  # noqa: E731
    return _mode(run, jnp.array([1.0]), mode)


def case_singular_midrun(mode):
    # M = q², singular at q = 0, reached at t = 0.5
    s = jl.System(lambda q, qd: 0.5 * q[0] ** 2 * qd[0] ** 2)
    run = lambda q0: jl.simulate(s, q0, jnp.array([-1.0]), TS).q  # noqa: E731
    return _mode(run, jnp.array([1.0]), mode)


def case_nan_length(mode):
    s = cartesian_pendulum()
    run = lambda l: (
        jl.simulate(
            s,
            jnp.array([1.0, 0.0]),
            jnp.zeros(2),
            TS,  # noqa: E731
            args={"g": 9.81, "l": l},
        ).q
    )
    return _mode(run, jnp.array(jnp.nan), mode)


def case_batch_one_nan(mode):
    s = cartesian_pendulum()
    q0s = jnp.array([[1.0, 0.0], [jnp.nan, 0.0], [0.0, -1.0]])
    run = lambda q0s: (
        jl.simulate_batch(
            s,
            q0s,
            jnp.zeros(2),
            TS,  # noqa: E731
            args={"g": 9.81, "l": 1.0},
        ).q
    )
    if mode == "vmap":
        return "n/a"
    return _mode(run, q0s, "jit" if mode == "jit" else "eager")


def case_args_missing(mode):
    s = cartesian_pendulum()
    run = lambda q0: jl.simulate(s, q0, jnp.zeros(2), TS).q  # noqa: E731
    return _mode(run, jnp.array([1.0, 0.0]), mode)


def case_repeated_ts(mode):
    s = pendulum_free()
    ts = jnp.array([0.0, 0.5, 0.5, 1.0])
    run = lambda ts: jl.simulate(s, jnp.array([0.3]), jnp.zeros(1), ts).q  # noqa: E731
    if mode == "vmap":
        return _mode(run, ts[None], "vmap")
    return _mode(run, ts, mode)


def case_max_steps(mode):
    s = cartesian_pendulum()
    ts = jnp.linspace(0.0, 2000.0, 3)
    run = lambda q0: jl.simulate(s, q0, jnp.zeros(2), ts, args={"g": 9.81, "l": 1.0}).q  # noqa: E731
    return _mode(run, jnp.array([1.0, 0.0]), mode)


def _mode(fn, x, mode):
    if mode == "eager":
        out = fn(x)
    elif mode == "jit":
        out = jax.jit(fn)(x)
    elif mode == "vmap":
        out = jax.vmap(fn)(x[None] if mode == "vmap" and x.ndim < 2 else x)
    jax.block_until_ready(out)
    if out.ndim <= 1 and out.size == 1:
        return f"ok (no error): {float(out.reshape(())):.6g}"
    if not bool(jnp.all(jnp.isfinite(out))):
        return "no error; NaN/inf in the result"
    return "ok (no error)"


FLOAT32 = textwrap.dedent("""
    import jax, jax.numpy as jnp, jaxlag as jl
    def L(q, qd): return 0.5 * (qd @ qd) - 9.81 * q[1]
    s = jl.System(L, holonomic=lambda q: jnp.array([q @ q - 1.0]))
    q0 = jnp.array([jnp.sin(0.3), -jnp.cos(0.3)])
    jl.simulate(s, q0, jnp.zeros(2), jnp.linspace(0, 1, 11))
    print("ok (no error)")
""")


def case_float32(mode):
    if mode != "eager":
        return "n/a"
    r = subprocess.run([sys.executable, "-c", FLOAT32], capture_output=True, text=True)
    if r.returncode == 0:
        return r.stdout.strip()
    last = [line for line in r.stderr.strip().splitlines() if line.strip()][-1]
    return last


CASES = {
    "1 event, no constraints": case_event_unconstrained,
    "2 NaN in args": case_nan_args,
    "2 NaN mid-run (q**1.5)": case_nan_midrun,
    "2 M singular mid-run": case_singular_midrun,
    "2 NaN length": case_nan_length,
    "2 batch, one NaN member": case_batch_one_nan,
    "3 float32 constrained": case_float32,
    "5 args missing": case_args_missing,
    "5 repeated save times": case_repeated_ts,
    "6 1000 periods, max_steps": case_max_steps,
}


def describe(exc: BaseException, width: int) -> str:
    text = " ".join(str(exc).split())
    marker = "jaxlag:"
    if marker in text:  # under jit the library's text sits at the end of a runtime error
        text = "…" + text[text.index(marker) :]
    return f"{type(exc).__name__}: {text[:width]}"


def main(width: int = 150):
    print("| case | mode | what the user sees |")
    print("|---|---|---|")
    for name, case in CASES.items():
        for mode in ("eager", "jit", "vmap"):
            try:
                result = case(mode)
            except Exception as exc:  # noqa: BLE001 - the catalogue reports every failure
                result = describe(exc, width)
            print(f"| {name} | {mode} | {result.replace('|', '/')} |", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 150)
