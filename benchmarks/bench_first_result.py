"""Time to the first result: what a research script pays before its first number.

Each stage runs in a fresh Python process (pinned to one core), as a user's script would: the
import, then each step of the stage, timed by wall clock, with the compilation work of that step
from ``jax.monitoring`` (tracing ``jaxpr_trace_duration``, lowering
``jaxpr_to_mlir_module_duration``, XLA ``backend_compile_duration``, and the number of XLA
compilations). Every stage is then run twice more with JAX's persistent compilation cache in a
fresh directory, turned on as a user would: ``jl.enable_compilation_cache(directory)`` right
after ``import jaxlag`` (the hand-written reference sets ``jax_compilation_cache_dir`` itself).
The first of those fills the cache, the second ("cached") is what the second run of the same
script costs. The fresh runs have no persistent cache.

The hand-written reference (a double pendulum's explicit equations of motion under
``diffrax.diffeqsolve``, written directly in ``jax.numpy``) is measured the same way, in the same
run: the ratios against it are the numbers to compare between runs.

    python -m benchmarks.bench_first_result            # all stages, about 3-5 minutes
    python -m benchmarks.bench_first_result readme fit   # some stages
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import textwrap

PRELUDE = textwrap.dedent('''
    import os, time, json, sys
    _t_start = time.perf_counter()
    try:
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[-1]})
    except (AttributeError, OSError):
        pass
    import jax
    jax.config.update("jax_enable_x64", True)
    if os.environ.get("BENCH_CACHE_DIR"):
        if os.environ.get("BENCH_STAGE") == "hand":
            jax.config.update("jax_compilation_cache_dir", os.environ["BENCH_CACHE_DIR"])
            jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        else:
            import jaxlag as _jl
            _jl.enable_compilation_cache(os.environ["BENCH_CACHE_DIR"])
    _events = {"trace": 0.0, "lower": 0.0, "xla": 0.0, "compiles": 0}
    _names = {"/jax/core/compile/jaxpr_trace_duration": "trace",
              "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
              "/jax/core/compile/backend_compile_duration": "xla"}
    def _listen(event, duration, **kwargs):
        key = _names.get(event)
        if key is not None:
            _events[key] += duration
            if key == "xla":
                _events["compiles"] += 1
    jax.monitoring.register_event_duration_secs_listener(_listen)
    _events["hits"] = 0
    def _count(event, **kwargs):
        if event == "/jax/compilation_cache/cache_hits":
            _events["hits"] += 1
    jax.monitoring.register_event_listener(_count)
    import jax.numpy as jnp
    import numpy as np
    _t_prev = [_t_start, dict(_events)]
    def step(name):
        """Record the time and compilation work since the previous step."""
        now = time.perf_counter()
        t_prev, e_prev = _t_prev
        row = {"step": name, "wall": now - t_prev}
        row.update({k: _events[k] - e_prev[k] for k in _events})
        print("ROW " + json.dumps(row), flush=True)
        _t_prev[:] = [time.perf_counter(), dict(_events)]
''')

STAGES = {
    "hand": """
        import diffrax
        step("import")
        def field(t, y, args):
            th1, th2, w1, w2 = y
            g, l, m = 9.81, 1.0, 1.0
            d = th1 - th2
            den = 2 * m + m - m * jnp.cos(2 * d)
            a1 = (-g * (2 * m + m) * jnp.sin(th1) - m * g * jnp.sin(th1 - 2 * th2)
                  - 2 * jnp.sin(d) * m * (w2**2 * l + w1**2 * l * jnp.cos(d))) / (l * den)
            a2 = (2 * jnp.sin(d) * (w1**2 * l * (m + m) + g * (m + m) * jnp.cos(th1)
                  + w2**2 * l * m * jnp.cos(d))) / (l * den)
            return jnp.stack([w1, w2, a1, a2])
        def solve(y0):
            return diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, 2.0, None,
                                       y0, saveat=diffrax.SaveAt(ts=jnp.linspace(0, 2, 201)),
                                       stepsize_controller=diffrax.PIDController(rtol=1e-10,
                                                                                 atol=1e-10)).ys
        jax.block_until_ready(solve(jnp.array([0.3, 0.2, 0.0, 0.0])))
        step("first solve")
        g = jax.grad(lambda y0: jnp.sum(solve(y0)[:, 0] ** 2))(jnp.array([0.3, 0.2, 0.0, 0.0]))
        jax.block_until_ready(g)
        step("first grad")
    """,
    "readme": """
        import jaxlag as jl
        step("import")
        def lagrangian(q, qd, args):
            r, th = q
            rd, thd = qd
            m, g = args["m"], args["g"]
            return 0.5 * m * (rd**2 + r**2 * thd**2) - m * g * r * jnp.cos(th)
        def on_sphere(q, args):
            return jnp.array([q[0] - args["R"]])
        system = jl.System(lagrangian, holonomic=on_sphere)
        args = {"m": 1.0, "g": 9.81, "R": 2.0}
        traj = jl.simulate(system, jnp.array([2.0, 0.1]), jnp.zeros(2), jnp.linspace(0, 2, 201),
                           args=args)
        jax.block_until_ready(traj.q)
        step("first simulate")
        jax.block_until_ready(traj.multipliers)
        step("multipliers")
        loss = lambda a: jnp.sum(jl.simulate(system, jnp.array([2.0, 0.1]), jnp.zeros(2),
                                             jnp.linspace(0, 1, 11), args=a).q[:, 1] ** 2)
        jax.block_until_ready(jax.grad(loss)(args))
        step("first grad")
        jax.block_until_ready(jl.simulate(system, jnp.array([2.0, 0.2]), jnp.zeros(2),
                                          jnp.linspace(0, 2, 201), args=args).q)
        step("second simulate")
    """,
    "grad": """
        import jaxlag as jl
        step("import")
        pendulum = jl.System(lambda q, qd, args: 0.5 * args["l"] ** 2 * qd[0] ** 2
                             + args["g"] * args["l"] * jnp.cos(q[0]))
        ts = jnp.linspace(0.0, 2.0, 21)
        loss = lambda a: jnp.sum(jl.simulate(pendulum, jnp.array([0.5]), jnp.zeros(1), ts,
                                             args=a).q ** 2)
        jax.block_until_ready(jax.grad(loss)({"g": 9.81, "l": 1.0}))
        step("first grad")
    """,
    "fit": """
        import jaxlag as jl
        step("import")
        pendulum = jl.System(lambda q, qd, args: 0.5 * args["l"] ** 2 * qd[0] ** 2
                             + args["g"] * args["l"] * jnp.cos(q[0]))
        def bob(q, qd, args):
            return args["l"] * jnp.array([jnp.sin(q[0]), -jnp.cos(q[0])])
        ts = jnp.linspace(0.0, 2.0, 41)
        truth = {"g": 9.81, "l": 0.8}
        traj = jl.simulate(pendulum, jnp.array([0.5]), jnp.zeros(1), ts, args=truth)
        data = jax.vmap(lambda q, qd: bob(q, qd, truth))(traj.q, traj.qd)
        step("data")
        experiment = jl.Experiment(ts, data, jnp.array([0.5]), jnp.zeros(1))
        result = jl.fit(pendulum, {"g": 11.0, "l": 0.6}, experiment, observe=bob,
                        transforms={"g": jl.Positive(), "l": jl.Positive()})
        jax.block_until_ready(result.params)
        step("first fit (2 parameters)")
    """,
    "batch": """
        import jaxlag as jl
        step("import")
        pendulum = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 + args["g"] * jnp.cos(q[0]))
        q0s = jnp.linspace(0.1, 1.0, 64)[:, None]
        traj = jl.simulate_batch(pendulum, q0s, jnp.zeros(1), jnp.linspace(0, 2, 21),
                                 args={"g": 9.81})
        jax.block_until_ready(traj.q)
        step("first simulate_batch (B = 64)")
    """,
    "demo": """
        import runpy, matplotlib
        matplotlib.use("Agg")
        step("import")
        sys.argv = ["demo.py"]
        import contextlib, io
        with contextlib.redirect_stdout(io.StringIO()):
            runpy.run_path(os.path.join("examples", "demo.py"), run_name="__main__")
        step("examples/demo.py")
    """,
}


def run_stage(name: str, cache_dir: str | None) -> list[dict]:
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    env.pop("BENCH_CACHE_DIR", None)
    env["BENCH_STAGE"] = name
    if cache_dir is not None:
        env["BENCH_CACHE_DIR"] = cache_dir
        env["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    code = PRELUDE + textwrap.dedent(STAGES[name]) + '\nstep("exit")\n'
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env=env,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    )
    if out.returncode != 0:
        raise RuntimeError(f"stage {name} failed:\n{out.stderr[-3000:]}")
    return [json.loads(line[4:]) for line in out.stdout.splitlines() if line.startswith("ROW ")]


def _total(rows):
    return sum(r["wall"] for r in rows if r["step"] != "exit")


def main(names=None) -> None:
    names = names or list(STAGES)
    print(
        "Time to first result (fresh process per stage, one core). Seconds; compiles = XLA "
        "compilations in that step.\n"
    )
    print("| stage | step | wall | trace | lower | XLA | compiles | cached wall | cached XLA | cache hits |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    totals = {}
    for name in names:
        fresh = run_stage(name, None)
        with tempfile.TemporaryDirectory() as cache:
            run_stage(name, cache)  # fills the cache
            cached = run_stage(name, cache)
        by_step = {r["step"]: r for r in cached}
        for r in fresh:
            if r["step"] == "exit":
                continue
            c = by_step.get(r["step"], {})
            print(
                f"| {name} | {r['step']} | {r['wall']:.2f} | {r['trace']:.2f} | {r['lower']:.2f} "
                f"| {r['xla']:.2f} | {r['compiles']} | {c.get('wall', float('nan')):.2f} "
                f"| {c.get('xla', float('nan')):.2f} | {c.get('hits', '-')} |",
                flush=True,
            )
        totals[name] = (_total(fresh), _total(cached))
        print(
            f"| {name} | **total** | **{totals[name][0]:.2f}** | | | | | **{totals[name][1]:.2f}** | | |",
            flush=True,
        )
    if "hand" in totals:
        hand = totals["hand"][0]
        print("\nTotal wall time relative to the hand-written diffrax reference (same run):")
        for name, (fresh, cached) in totals.items():
            print(f"  {name:8s} {fresh / hand:5.2f}x fresh, {cached / hand:5.2f}x cached")


if __name__ == "__main__":
    main(sys.argv[1:] or None)
