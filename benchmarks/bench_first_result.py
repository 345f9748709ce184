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
run: the ratios against it are the numbers to compare between runs. ``batch1000`` (one
``jl.simulate_batch`` of 1,000 pendulums) has its own reference, ``batch_hand``: ``jax.jit`` of
``jax.vmap`` of ``diffrax.diffeqsolve`` on the same pendulum, with the same solver (Tsit5),
controller (PID, rtol = atol = 1e-10), ``max_steps`` and save times. ``fit_demo`` is the fit of the
README's demo (``examples/demo.py``: ``g`` and ``R`` of a particle on a sphere from noisy camera
positions), ``fit`` the pendulum of the fitting cookbook page. ``learned`` is a learned model's
first steps (``jaxlag.learned``: a double pendulum's states and accelerations, a DeLaN, its first
acceleration loss and 20 training steps), to compare against a baseline checkout. Each row also
gives the CPU time of the process (all its threads), which a shared machine disturbs less than
the wall clock; steps named ``after: ...`` (a second call, for its run time) are left out of the
totals.

    python -m benchmarks.bench_first_result            # all stages, about 3-5 minutes
    python -m benchmarks.bench_first_result readme fit   # some stages

Against an older commit (``--baseline``: a checkout whose ``src`` goes first on ``PYTHONPATH``; the
stages use only API that both have), ``--repeat`` rounds alternating the two trees, every ratio
taken within a round and the medians printed last (``--this``: measure another checkout instead of
this one, e.g. a worktree of a commit while this working tree changes)::

    git worktree add --detach ../jaxlag-910a34b 910a34b
    python -m benchmarks.bench_first_result --baseline ../jaxlag-910a34b --repeat 3 batch1000 batch_hand
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
        if os.environ.get("BENCH_STAGE", "").endswith("hand"):
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
    _t_prev = [_t_start, dict(_events), 0.0]
    def step(name):
        """Record the time and compilation work since the previous step: wall clock, and the
        CPU time of the process (all its threads; on a shared machine it varies less)."""
        now, cpu = time.perf_counter(), time.process_time()
        t_prev, e_prev, cpu_prev = _t_prev
        row = {"step": name, "wall": now - t_prev, "cpu": cpu - cpu_prev}
        row.update({k: _events[k] - e_prev[k] for k in _events})
        print("ROW " + json.dumps(row), flush=True)
        _t_prev[:] = [time.perf_counter(), dict(_events), time.process_time()]
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
    "batch1000": """
        import jaxlag as jl
        step("import")
        pendulum = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 + args["g"] * jnp.cos(q[0]))
        q0s = jnp.linspace(0.1, 1.0, 1000)[:, None]
        traj = jl.simulate_batch(pendulum, q0s, jnp.zeros(1), jnp.linspace(0, 2, 21),
                                 args={"g": 9.81})
        jax.block_until_ready(traj.q)
        step("first simulate_batch (B = 1000)")
        jax.block_until_ready(jl.simulate_batch(pendulum, q0s + 0.01, jnp.zeros(1),
                                                jnp.linspace(0, 2, 21), args={"g": 9.81}).q)
        step("after: second simulate_batch")
    """,
    "batch_hand": """
        import diffrax
        step("import")
        def field(t, y, args):
            return jnp.stack([y[1], -args["g"] * jnp.sin(y[0])])
        def solve(y0, args, ts):
            return diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Tsit5(), ts[0], ts[-1], None,
                                       y0, args=args, saveat=diffrax.SaveAt(ts=ts), max_steps=2**16,
                                       stepsize_controller=diffrax.PIDController(rtol=1e-10,
                                                                                 atol=1e-10)).ys
        batch = jax.jit(jax.vmap(solve, in_axes=(0, None, None)))
        q0s = jnp.linspace(0.1, 1.0, 1000)[:, None]
        y0s = jnp.concatenate([q0s, jnp.zeros_like(q0s)], axis=1)
        jax.block_until_ready(batch(y0s, {"g": 9.81}, jnp.linspace(0, 2, 21)))
        step("first vmap of diffeqsolve (B = 1000)")
        jax.block_until_ready(batch(y0s + 0.01, {"g": 9.81}, jnp.linspace(0, 2, 21)))
        step("after: second vmap of diffeqsolve")
    """,
    "learned": """
        import jaxlag as jl
        from jaxlag import learned as jll
        step("import")
        truth = jl.systems.double_pendulum()
        q = jax.random.uniform(jax.random.PRNGKey(0), (10, 41, 2), minval=-1.0, maxval=1.0)
        ts = jnp.broadcast_to(jnp.linspace(0.0, 2.0, 41), (10, 41))
        data = jll.TrajectoryData(ts, q, q[::-1])
        states = jll.state_data(truth, data)
        model = jll.DeLaN(2, 16, 2, key=jax.random.PRNGKey(1))
        jax.block_until_ready(states.qdd)
        step("data and model")
        jax.block_until_ready(jll.AccelerationLoss()(model, states).value)
        step("first loss")
        result = jll.train(model, jll.AccelerationLoss(), states, steps=20)
        jax.block_until_ready(result.model)
        step("train 20 steps")
    """,
    "fit_demo": """
        import jaxlag as jl
        step("import")
        def lagrangian(q, qd, args):
            r, theta = q
            rd, thetad = qd
            m, g = args["m"], args["g"]
            return 0.5 * m * (rd**2 + r**2 * thetad**2) - m * g * r * jnp.cos(theta)
        def on_sphere(q, args):
            return jnp.array([q[0] - args["R"]])
        def camera(q, qd):
            return q[0] * jnp.array([jnp.sin(q[1]), jnp.cos(q[1])])
        true = {"m": 1.0, "g": 9.81, "R": 2.0}
        q0, qd0 = jnp.array([true["R"], 0.05]), jnp.array([0.0, 0.0])
        window = np.linspace(0.0, 2.6, 261)[:155]  # examples/demo.py: until 0.05 s before release
        on_the_sphere = jl.System(lagrangian, holonomic=on_sphere)
        q = np.asarray(jl.simulate(on_the_sphere, q0, qd0, window, args=true).q)
        clean = q[:, :1] * np.stack([np.sin(q[:, 1]), np.cos(q[:, 1])], axis=1)
        observed = clean + 0.002 * np.random.default_rng(0).standard_normal(clean.shape)
        step("data")
        result = jl.fit(on_the_sphere, {"g": 8.0, "R": 2.4}, jl.Experiment(window, observed, q0, qd0),
                        observe=camera, args={"m": 1.0},
                        transforms={"g": jl.Positive(), "R": jl.Positive()})
        fitted = {k: (float(result.params[k]), float(result.standard_errors[k])) for k in ("g", "R")}
        step("fit (g, R)")
        print("FITTED " + json.dumps(fitted), flush=True)
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


#: The hand-written reference of each stage (the others: ``hand``).
REFERENCE = {"batch1000": "batch_hand"}


def _is_reference(name: str) -> bool:
    return name.endswith("hand")


def run_stage_lines(
    name: str, cache_dir: str | None, src: str | None = None
) -> tuple[list[dict], dict[str, object]]:
    """The rows of one stage in a fresh process, and what it printed as ``KEY {json}`` lines
    other than its rows (``FITTED``: the fitted values). ``src``: the ``src`` directory of
    another checkout of jaxlag, put first on ``PYTHONPATH`` (the stage then imports that
    jaxlag: the same script against an older commit)."""
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    env.pop("BENCH_CACHE_DIR", None)
    env["BENCH_STAGE"] = name
    if src is not None:
        env["PYTHONPATH"] = os.pathsep.join([src, *filter(None, [env.get("PYTHONPATH")])])
    if cache_dir is not None:
        env["BENCH_CACHE_DIR"] = cache_dir
        env["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    code = PRELUDE + textwrap.dedent(STAGES[name]) + '\nstep("exit")\n'
    code += (
        'print("JAXLAG " + json.dumps(sys.modules["jaxlag"].__file__ if "jaxlag" in sys.modules else None))\n'
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env=env,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    )
    if out.returncode != 0:
        raise RuntimeError(f"stage {name} failed:\n{out.stderr[-3000:]}")
    rows, extra = [], {}
    for line in out.stdout.splitlines():
        key, _, value = line.partition(" ")
        if key == "ROW":
            rows.append(json.loads(value))
        elif key.isupper() and value.startswith(("{", "[", '"', "null")):
            extra[key] = json.loads(value)
    return rows, extra


def run_stage(name: str, cache_dir: str | None, src: str | None = None) -> list[dict]:
    return run_stage_lines(name, cache_dir, src)[0]


def _total(rows, key="wall"):
    """The stage's wall time (``key="cpu"``: CPU time): every step but ``exit`` and the
    ``after: ...`` steps (a second call, shown for its run time, not part of the first result)."""
    return sum(
        r.get(key, float("nan")) for r in rows if r["step"] != "exit" and not r["step"].startswith("after:")
    )


def _print_rows(label, fresh, cached) -> None:
    by_step = {r["step"]: r for r in cached}
    for r in fresh:
        if r["step"] == "exit":
            continue
        c = by_step.get(r["step"], {})
        print(
            f"| {label} | {r['step']} | {r['wall']:.2f} | {r.get('cpu', float('nan')):.2f} "
            f"| {r['trace']:.2f} | {r['lower']:.2f} "
            f"| {r['xla']:.2f} | {r['compiles']} | {c.get('wall', float('nan')):.2f} "
            f"| {c.get('cpu', float('nan')):.2f} | {c.get('xla', float('nan')):.2f} "
            f"| {c.get('compiles', '-')} | {c.get('hits', '-')} |",
            flush=True,
        )
    print(
        f"| {label} | **total** | **{_total(fresh):.2f}** | **{_total(fresh, 'cpu'):.2f}** | | | | "
        f"| **{_total(cached):.2f}** | **{_total(cached, 'cpu'):.2f}** | | | |",
        flush=True,
    )


_HEADER = (
    "| stage | step | wall | CPU | trace | lower | XLA | compiles | cached wall | cached CPU | cached XLA "
    "| cached compiles | cache hits |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|"
)


def _fresh_and_cached(name: str, src: str | None = None):
    fresh, extra = run_stage_lines(name, None, src)
    with tempfile.TemporaryDirectory() as cache:
        run_stage(name, cache, src)  # fills the cache
        cached = run_stage(name, cache, src)
    return fresh, cached, extra


def main(names=None) -> None:
    names = names or list(STAGES)
    print(
        "Time to first result (fresh process per stage, one core). Seconds; compiles = XLA "
        "compilations in that step.\n"
    )
    print(_HEADER)
    totals = {}
    for name in names:
        fresh, cached, _ = _fresh_and_cached(name)
        _print_rows(name, fresh, cached)
        totals[name] = (_total(fresh), _total(cached))
    refs = {name: REFERENCE.get(name, "hand") for name in totals if not _is_reference(name)}
    if any(ref in totals for ref in refs.values()):
        print(
            "\nTotal wall time relative to the hand-written diffrax reference (same run; cached: "
            "jaxlag's second process against the reference's fresh one):"
        )
        for name, ref in refs.items():
            if ref in totals:
                (fresh, cached), hand = totals[name], totals[ref][0]
                print(f"  {name:10s} {fresh / hand:5.2f}x fresh, {cached / hand:5.2f}x cached  (vs {ref})")


def _median(values):
    values = sorted(values)
    mid = len(values) // 2
    return values[mid] if len(values) % 2 else 0.5 * (values[mid - 1] + values[mid])


def compare(
    names: list[str], baseline: str, repeat: int, json_path: str | None = None, this: str | None = None
) -> None:
    """Each stage against the same stage run on the checkout ``baseline`` (its ``src`` first on
    ``PYTHONPATH``) and against its hand-written reference when that is among ``names`` (the
    references run on this tree only: they do not import jaxlag): ``repeat`` rounds, the contenders
    alternated (this tree first in even rounds, the baseline first in odd ones), every ratio
    taken within a round, and the medians of the rounds printed at the end. ``this``: another
    checkout to measure instead of this one (e.g. a worktree of a commit, while this working
    tree changes)."""
    src = os.path.join(os.path.abspath(baseline), "src")
    this_src = None if this is None else os.path.join(os.path.abspath(this), "src")
    for tree in filter(None, (src, this_src)):
        if not os.path.isdir(os.path.join(tree, "jaxlag")):
            raise SystemExit(f"{os.path.dirname(tree)} has no src/jaxlag")
    runs = []
    print(_HEADER)
    for round_ in range(repeat):
        record: dict[str, dict] = {}
        for name in names:
            trees = [("this", this_src)] if _is_reference(name) else [("this", this_src), ("base", src)]
            if round_ % 2:
                trees.reverse()
            for tree, tree_src in trees:
                fresh, cached, extra = _fresh_and_cached(name, tree_src)
                label = f"{name} ({tree}, round {round_ + 1})"
                _print_rows(label, fresh, cached)
                if "FITTED" in extra:
                    print(f"  {label}: fitted {extra['FITTED']}", flush=True)
                record[f"{name}/{tree}"] = {
                    "fresh": _total(fresh),
                    "cached": _total(cached),
                    "fresh_cpu": _total(fresh, "cpu"),
                    "cached_cpu": _total(cached, "cpu"),
                    "fresh_rows": fresh,
                    "cached_rows": cached,
                    **({"fitted": extra["FITTED"]} if "FITTED" in extra else {}),
                }
        runs.append(record)
    print(
        f"\nRatios within each round ({repeat} rounds; medians last). this = {this or os.getcwd()}, "
        f"base = {baseline}. cached: the second process with jl.enable_compilation_cache().\n"
    )
    print("| stage | ratio | " + " | ".join(f"round {i + 1}" for i in range(repeat)) + " | median |")
    print("|---|---|" + "---|" * (repeat + 1))
    summary = {}
    for name in names:
        if _is_reference(name):
            continue
        ref = REFERENCE.get(name, "hand")
        for unit, suffix in (("wall", ""), ("CPU", "_cpu")):

            def total(r, stage, tree, kind, suffix=suffix):
                return r[f"{stage}/{tree}"][kind + suffix]

            ratios: dict = {
                "this/base fresh": lambda r: (
                    total(r, name, "this", "fresh") / total(r, name, "base", "fresh")
                ),
                "this/base cached": lambda r: (
                    total(r, name, "this", "cached") / total(r, name, "base", "cached")
                ),
                f"this/{ref} fresh": lambda r: (
                    total(r, name, "this", "fresh") / total(r, ref, "this", "fresh")
                ),
                f"this cached/{ref} fresh": lambda r: (
                    total(r, name, "this", "cached") / total(r, ref, "this", "fresh")
                ),
                f"this cached/{ref} cached": lambda r: (
                    total(r, name, "this", "cached") / total(r, ref, "this", "cached")
                ),
                f"base/{ref} fresh": lambda r: (
                    total(r, name, "base", "fresh") / total(r, ref, "this", "fresh")
                ),
                f"base cached/{ref} fresh": lambda r: (
                    total(r, name, "base", "cached") / total(r, ref, "this", "fresh")
                ),
            }
            if ref not in names:  # no reference in this run: the ratios to the baseline only
                ratios = {k: v for k, v in ratios.items() if k.startswith("this/base")}
            for label, ratio in ratios.items():
                values = [ratio(r) for r in runs]
                summary[f"{name}: {label} ({unit})"] = _median(values)
                cells = " | ".join(f"{v:.2f}" for v in values)
                print(f"| {name} | {label} ({unit}) | {cells} | **{_median(values):.2f}** |")
    print("\nMedian seconds (wall; CPU):")
    for key in runs[0]:
        med = {k: _median([r[key][k] for r in runs]) for k in ("fresh", "cached", "fresh_cpu", "cached_cpu")}
        print(
            f"  {key:22s} fresh {med['fresh']:6.2f} s; {med['fresh_cpu']:6.2f} s, "
            f"cached {med['cached']:6.2f} s; {med['cached_cpu']:6.2f} s"
        )
    if json_path:
        with open(json_path, "w") as f:
            json.dump({"baseline": baseline, "runs": runs, "median_ratios": summary}, f, indent=1)


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("stages", nargs="*", help=f"any of {', '.join(STAGES)} (default: all)")
    parser.add_argument("--baseline", help="another checkout of jaxlag to run the same stages against")
    parser.add_argument("--repeat", type=int, default=1, help="rounds with --baseline (medians of them)")
    parser.add_argument("--json", help="with --baseline: write every round's figures here")
    parser.add_argument("--this", help="with --baseline: measure this checkout instead of the current one")
    cli = parser.parse_args()
    if cli.baseline:
        compare(
            cli.stages or [n for n in STAGES if n != "demo"], cli.baseline, cli.repeat, cli.json, cli.this
        )
    else:
        main(cli.stages or None)
