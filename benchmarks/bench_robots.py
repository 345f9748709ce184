"""Robots (issue 38): the recursive algorithms of ``jaxlag.robots`` against the autodiff path, and
a batch of arms against MuJoCo's own C loop.

``jlr.system(tree)`` takes its ``M`` and the forces of ``L`` from ``jlr.TreeDynamics`` (composite
rigid bodies + Newton–Euler, for every tree, ball and free joints included: the *recursive*
path); ``jlr.system(tree, dynamics=jl.AutodiffDynamics())`` forms them by automatic differentiation of
``L = T − V`` (``jl.AutodiffDynamics``: the *autodiff* path, the only one before). Both are
measured side by side in the chain and the floating-base parts.

**Chain of N links** (N = 10, 50, 100, 200; a hinge chain generated as MJCF: each link a capsule
of 0.1 m and 0.1 kg hanging from the previous one, axis y, damping 0.05, contacts off). Every
contender integrates the same constant-step explicit RK4 (a diffrax ``AbstractERK`` with the
classical tableau, 4 evaluations of the right-hand side per step), ``STEPS`` steps of
``DT``, ``SaveAt(t1=True)``:

* *ABA*: ``diffrax.diffeqsolve`` of ``(q, v) ↦ (v, jlr.forward_dynamics(tree, q, v))``;
* *CRBA + RNEA, dense solve*: ``jnp.linalg.solve(jlr.mass_matrix, −damping·v − jlr.bias_forces)``;
* *jl.simulate(jlr.system)*: the recursive path, ``jl.simulate`` of ``jlr.system(tree)`` (``M`` by
  composite rigid bodies, the forces by Newton–Euler, then jaxlag's dense solve of ``M q̈ = F``;
  default ``checks``, so the initial-state check is compiled in);
* *jl.simulate(jlr.system, articulated)*: the same with
  ``dynamics=jlr.ArticulatedBodyDynamics(tree)``: ``M`` never formed, ``M⁻¹`` applied by the
  articulated-body algorithm (O(N) per step);
* *jl.simulate(jlr.system, autodiff)*: the same with ``jlr.system(tree, dynamics=jl.AutodiffDynamics())``,
  ``M = ∂²L/∂q̇²`` and ``F = ∂L/∂q − (∂²L/∂q̇∂q) q̇`` by automatic differentiation of the tree's
  ``L = T − V`` (the path every ``jlr.system`` took before ``TreeDynamics``);
* *jl.System(hand L)*: benchmarks/bench_unconstrained.py's planar chain of unit point masses in
  absolute angles, ``L`` by cumulative sums (a different model with the same N: a cost reference
  of the autodiff path on the smallest hand-written ``L``);
* *hand M, solve* (the hand-written baseline of the ratios): the same planar chain's
  ``M_ij = (N − max(i, j)) cos(θi − θj)`` and right-hand side, ``jnp.linalg.solve``.

*First result*: each contender at each N in a fresh Python process pinned to one core (import,
``jlr.load``, the first ``jax.jit`` call of the solve and its result), wall clock and the
process's CPU time, with the tracing, lowering and XLA seconds from ``jax.monitoring``. A
contender whose fresh process passes ``BENCH_ROBOTS_CAP`` seconds (default 240) is stopped and
skipped at the larger N. *Per step*: every surviving contender at that N compiled in this
process and timed alternately (median of ``REPEATS`` rounds; wall and CPU time per sample), µs
per RK4 step; the exponent ``p`` of ``cost ∝ N^p`` is a least-squares line through
``(log N, log cost)``.

**Batch of 1,024 arms** (the 7-DoF arm of tests/test_robots.py: damping, armature, contacts off,
zero controls), ``BATCH_STEPS`` fixed steps of ``DT``, float64, one core, in state-steps per
second (``B × steps / time``):

* *MuJoCo RK4* and *MuJoCo Euler*: ``mujoco.rollout.rollout`` (many ``mj_step`` in C, one MjData
  so one thread) with ``opt.integrator`` = ``mjINT_RK4`` (classical explicit RK4, like ours) or
  ``mjINT_EULER`` (semi-implicit Euler with implicitly integrated damping: one ``mj_forward`` per
  step). Its output (every state of every step) is written by the C loop and counted in its time;
* *vmap(ABA), RK4*: ``jax.vmap`` of the ABA vector field's ``diffrax.diffeqsolve`` (our RK4);
* *vmap(CRBA + RNEA, dense solve), RK4*;
* *simulate_batch(jlr.system), RK4*: ``jl.simulate_batch`` of the recursive path.

The final states of MuJoCo RK4 and ours are compared (the same integrator, so they agree to
rounding). Ratios are ``state-steps/s of ours / MuJoCo RK4`` in the same rounds, by wall clock
and by CPU time.

**Floating base** (K = 5, 15, 40; generated as MJCF): a free-joint base, a 5 kg box of
0.4 × 0.2 × 0.1 m, carrying two legs of K hinges each (capsules of 0.1 m and 0.1 kg hanging
along −z, axes alternating y, x, damping 0.05, contacts off, gravity on), so ``nq = 7 + 2K``
coordinates (the base position and unit quaternion, then the hinge angles) and ``nv = 6 + 2K``
velocities. The same RK4, ``STEPS`` steps of ``DT``, from a spinning, translating base with
swinging legs (``q̇`` from ``v`` by ``jlr.configuration_rate``):

* *jl.simulate(jlr.system)*: the recursive path (``TreeDynamics``: ``M = Gᵀ M_v G + Q Qᵀ`` and the
  forces by Newton–Euler mapped to ``q̇``), the quaternion's ``|Q|² − 1 = 0`` a holonomic row of
  jaxlag's KKT solve (and its projection);
* *jl.simulate(jlr.system, autodiff)*: the same system with ``dynamics=jl.AutodiffDynamics()``.

First result in a fresh process and per-step cost alternated as in the chain part; the speedup is
``CPU per step of autodiff / recursive``; the two final states (``q``, ``q̇``) must agree to about
1e-10, and the base quaternion's ``| |Q| − 1 |`` is reported.

Run: ``python -m benchmarks.bench_robots`` (chain, batch and floating; 20-40 minutes on the
loaded 2-core machine); ``python -m benchmarks.bench_robots chain``, ``batch`` or ``floating``
for one part (several may be named).
"""

from __future__ import annotations

import importlib
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any, ClassVar

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported

# isort: split
import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

SIZES = (5, 10) if common.QUICK else (10, 50, 100, 200)
FLOATING_SIZES = (2, 4) if common.QUICK else (5, 15, 40)  # K hinges per leg
STEPS = 20 if common.QUICK else 100
DT = 1e-3
BATCH = 64 if common.QUICK else 1024
BATCH_STEPS = 10 if common.QUICK else 50
CAP_S = float(os.environ.get("BENCH_ROBOTS_CAP", "240"))
#: A contender whose call (STEPS steps) is predicted past this many seconds at the next N, from its
#: cost at this N times (N_next / N)^2.5, is skipped there (the timing rounds would take minutes).
CALL_CAP_S = float(os.environ.get("BENCH_ROBOTS_CALL_CAP", "20"))
FIRST_RESULT_TARGET_S = 5.0  # issue 38: first result at N = 100

_NO_CONTACT = '<option><flag contact="disable"/></option>'

ARM = f"""<mujoco>{_NO_CONTACT}<default><joint damping="0.5" armature="0.1"/></default><worldbody>
  <body name="base" pos="0 0 0.3" euler="0 0 20"><geom type="cylinder" size="0.1 0.05"/>
  <body name="l1" pos="0 0 0.1"><joint name="j1" axis="0 0 1"/>
    <geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.05"/>
  <body name="l2" pos="0 0 0.3" quat="0.9 0.1 0.3 -0.2"><joint name="j2" axis="0 1 0" pos="0 0 0.02"/>
    <geom type="box" size="0.04 0.05 0.2" pos="0.01 0.02 0.2"/>
  <body name="l3" pos="0 0 0.4"><joint name="j3" axis="0 0 1" armature="0.3"/>
    <geom type="capsule" fromto="0 0 0 0.05 0 0.3" size="0.04"/>
  <body name="l4" pos="0 0 0.3" euler="10 -20 5"><joint name="j4" axis="0.3 1 0.1" damping="1.2"/>
    <geom type="ellipsoid" size="0.05 0.08 0.15" pos="0 0 0.15" euler="5 10 15"/>
  <body name="l5" pos="0.02 0 0.3"><joint name="j5" axis="0 0 1"/>
    <geom type="capsule" fromto="0 0 0 0 0 0.2" size="0.03"/>
  <body name="l6" pos="0 0 0.2"><joint name="j6" axis="0 1 0" pos="0.01 0.01 0"/>
    <geom type="box" size="0.03 0.03 0.06" pos="0 0 0.06"/>
  <body name="l7" pos="0 0 0.12"><joint name="j7" axis="1 0 0"/>
    <geom type="cylinder" size="0.05 0.01" pos="0 0.02 0.01"/>
  </body></body></body></body></body></body></body></body>
</worldbody>
<actuator><motor joint="j1" gear="2"/><motor joint="j4"/><motor joint="j7" gear="0.5"/></actuator>
</mujoco>"""


def chain_xml(n: int) -> str:
    """A hinge chain of ``n`` capsules (0.1 m, 0.1 kg), hanging along −z, axes y."""
    body = (
        '<body pos="0 0 -0.1"><joint type="hinge" axis="0 1 0" damping="0.05"/>'
        '<geom type="capsule" fromto="0 0 0 0 0 -0.1" size="0.01" mass="0.1"/>'
    )
    first = body.replace('pos="0 0 -0.1"', 'pos="0 0 0"', 1)
    return f"<mujoco>{_NO_CONTACT}<worldbody>{first}{body * (n - 1)}{'</body>' * n}</worldbody></mujoco>"


def chain_state(n: int):
    i = jnp.arange(n, dtype=jnp.float64)
    return 0.3 * jnp.sin(0.7 * i + 0.4), 0.2 * jnp.cos(1.1 * i)


def floating_xml(k: int) -> str:
    """A free-joint base (a 5 kg box) carrying two legs of ``k`` hinges each (capsules of 0.1 m
    and 0.1 kg hanging along −z, axes alternating y, x)."""

    def leg(hip: str) -> str:
        links = []
        for j in range(k):
            pos = hip if j == 0 else "0 0 -0.1"
            axis = "0 1 0" if j % 2 == 0 else "1 0 0"
            links.append(
                f'<body pos="{pos}"><joint type="hinge" axis="{axis}" damping="0.05"/>'
                '<geom type="capsule" fromto="0 0 0 0 0 -0.1" size="0.01" mass="0.1"/>'
            )
        return "".join(links) + "</body>" * k

    base = '<body name="base" pos="0 0 1"><freejoint/><geom type="box" size="0.2 0.1 0.05" mass="5"/>'
    legs = leg("0.15 0 -0.05") + leg("-0.15 0 -0.05")
    return f"<mujoco>{_NO_CONTACT}<worldbody>{base}{legs}</body></worldbody></mujoco>"


def floating_state(tree, k: int):
    """``(q, q̇)``: the base 1 m up, tilted and spinning, the legs bent and swinging."""
    import jaxlag.robots as jlr

    i = jnp.arange(2 * k, dtype=jnp.float64)
    quaternion = jnp.array([0.9, 0.1, 0.2, 0.3])
    quaternion = quaternion / jnp.linalg.norm(quaternion)
    q = jnp.concatenate([jnp.array([0.0, 0.0, 1.0]), quaternion, 0.3 * jnp.sin(0.7 * i + 0.4)])
    v = jnp.concatenate([jnp.array([0.1, -0.2, 0.3, 0.5, -0.3, 0.2]), 0.2 * jnp.cos(1.1 * i)])
    return q, jlr.configuration_rate(tree, q, v)


# ----------------------------------------------------------------------------- RK4
_RK4_TABLEAU = diffrax.ButcherTableau(
    c=np.array([0.5, 0.5, 1.0]),
    b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
    b_error=np.array([1 / 6, 1 / 3, 1 / 3, -5 / 6]),  # unused: constant steps
    a_lower=(np.array([0.5]), np.array([0.0, 0.5]), np.array([0.0, 0.0, 1.0])),
)


class RK4(diffrax.AbstractERK):
    """The classical explicit fourth-order Runge–Kutta method (MuJoCo's ``mjINT_RK4``)."""

    tableau: ClassVar[diffrax.ButcherTableau | diffrax.MultiButcherTableau] = _RK4_TABLEAU
    interpolation_cls: ClassVar[Callable[..., Any]] = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        del terms
        return 4


def rk4_solve(acceleration: Callable, q0, v0, steps: int):
    """``(q(T), v(T))`` of ``q̇ = v, v̇ = acceleration(q, v)`` by ``steps`` RK4 steps of ``DT``."""

    def field(t, y, args):
        q, v = y
        return v, acceleration(q, v)

    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        RK4(),
        0.0,
        steps * DT,
        DT,
        (q0, v0),
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=steps + 1,
    )
    assert solution.ys is not None
    return solution.ys[0][-1], solution.ys[1][-1]


def simulate_kwargs(steps: int) -> dict:
    return dict(
        t0=0.0,
        t1=steps * DT,
        dt0=DT,
        saveat=diffrax.SaveAt(t1=True),
        solver=RK4(),
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=steps + 1,
    )


# ----------------------------------------------------------------------------- chain contenders
RECURSIVE = "jl.simulate(jlr.system)"
AUTODIFF = "jl.simulate(jlr.system, autodiff)"
ARTICULATED = "jl.simulate(jlr.system, articulated)"
CHAIN_CONTENDERS = (
    "hand M, solve",
    "ABA",
    "CRBA + RNEA, dense solve",
    RECURSIVE,
    ARTICULATED,
    AUTODIFF,
    "jl.System(hand L)",
)
BASELINE = "hand M, solve"
FLOATING_CONTENDERS = (RECURSIVE, ARTICULATED, AUTODIFF)


def _dynamics(name: str, tree):
    """The ``dynamics=`` of `jlr.system` for a contender (None: the default TreeDynamics)."""
    import jaxlag as jl
    import jaxlag.robots as jlr

    if name == ARTICULATED:
        return jlr.ArticulatedBodyDynamics(tree)
    return jl.AutodiffDynamics() if name == AUTODIFF else None


def chain_contender(name: str, n: int) -> tuple[Callable, tuple]:
    """``(solve, args)``: ``solve(q0, v0)`` gives the final state after ``STEPS`` RK4 steps."""
    import jaxlag as jl
    import jaxlag.robots as jlr

    from . import bench_unconstrained as bu

    if name in (BASELINE, "jl.System(hand L)"):
        q0, v0 = bu.chain_initial_state(n)
        if name == BASELINE:
            acceleration = bu.make_chain_solve(n)
            return (lambda q, v: rk4_solve(acceleration, q, v, STEPS)), (q0, v0)
        system = jl.System(bu.chain_lagrangian)
        return (lambda q, v: jl.simulate(system, q, v, **simulate_kwargs(STEPS)).q[-1]), (q0, v0)
    tree = jlr.load(chain_xml(n))
    q0, v0 = chain_state(n)
    if name == "ABA":
        return (lambda q, v: rk4_solve(lambda q, v: jlr.forward_dynamics(tree, q, v), q, v, STEPS)), (q0, v0)
    if name == "CRBA + RNEA, dense solve":

        def dense(q, v):
            rhs = -tree.damping * v - jlr.bias_forces(tree, q, v)
            return jnp.linalg.solve(jlr.mass_matrix(tree, q), rhs)

        return (lambda q, v: rk4_solve(dense, q, v, STEPS)), (q0, v0)
    if name in (RECURSIVE, ARTICULATED, AUTODIFF):
        system = jlr.system(tree, dynamics=_dynamics(name, tree))
        return (lambda q, v: jl.simulate(system, q, v, **simulate_kwargs(STEPS)).q[-1]), (q0, v0)
    raise ValueError(name)


def floating_contender(name: str, k: int) -> tuple[Callable, tuple]:
    """``(solve, args)``: ``solve(q0, q̇0)`` gives the final ``(q, q̇)`` after ``STEPS`` RK4 steps."""
    import jaxlag as jl
    import jaxlag.robots as jlr

    if name not in FLOATING_CONTENDERS:
        raise ValueError(name)
    tree = jlr.load(floating_xml(k))
    system = jlr.system(tree, dynamics=_dynamics(name, tree))

    def solve(q, qd):
        trajectory = jl.simulate(system, q, qd, **simulate_kwargs(STEPS))
        return trajectory.q[-1], trajectory.qd[-1]

    return solve, floating_state(tree, k)


BUILDERS: dict[str, Callable[[str, int], tuple[Callable, tuple]]] = {
    "chain": chain_contender,
    "floating": floating_contender,
}


def first_result_child(part: str, name: str, n: int) -> None:
    """In a fresh process: the time to the first result of one contender, as JSON on stdout."""
    events = {"trace": 0.0, "lower": 0.0, "xla": 0.0, "compiles": 0}
    keys = {
        "/jax/core/compile/jaxpr_trace_duration": "trace",
        "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
        "/jax/core/compile/backend_compile_duration": "xla",
    }

    def listen(event: str, duration_secs: float, **kwargs: str | int) -> None:
        key = keys.get(event)
        if key is not None:
            events[key] += duration_secs
            if key == "xla":
                events["compiles"] += 1

    jax.monitoring.register_event_duration_secs_listener(listen)
    import jaxlag  # noqa: F401
    import jaxlag.robots  # noqa: F401

    imported, imported_cpu = time.perf_counter(), time.process_time()
    solve, args = BUILDERS[part](name, n)
    jax.block_until_ready(jax.jit(solve)(*args))
    done, done_cpu = time.perf_counter(), time.process_time()
    row = {
        "import_s": imported - _T_START,
        "first_s": done - imported,
        "first_cpu_s": done_cpu - imported_cpu,
        "total_s": done - _T_START,
        "total_cpu_s": done_cpu,
        **events,
    }
    print("ROW " + json.dumps(row), flush=True)


def fresh_first_result(name: str, n: int, part: str = "chain") -> dict | None:
    """Run :func:`first_result_child` in a fresh process; ``None`` past ``CAP_S``."""
    command = [sys.executable, "-m", "benchmarks.bench_robots", "--first", part, name, str(n)]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=CAP_S, check=False)
    except subprocess.TimeoutExpired:
        return None
    for line in done.stdout.splitlines():
        if line.startswith("ROW "):
            return json.loads(line[4:])
    print(done.stdout[-2000:], done.stderr[-4000:], file=sys.stderr)
    raise RuntimeError(f"{part}: {name} at N = {n} failed in its fresh process")


def timed_alternating(calls: dict[str, Callable[[], Any]], repeats: int, min_sample_s: float = 0.2) -> dict:
    """Wall and CPU seconds per call, alternating the contenders; each sample ≥ ``min_sample_s``."""
    per_sample = {}
    for name, call in calls.items():
        start = time.perf_counter()
        jax.block_until_ready(call())
        one = time.perf_counter() - start
        per_sample[name] = max(1, int(min_sample_s / max(one, 1e-9)) + 1)
    samples: dict[str, dict[str, list[float]]] = {name: {"wall": [], "cpu": []} for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            k = per_sample[name]
            out = None
            wall, cpu = time.perf_counter(), time.process_time()
            for _ in range(k):
                out = call()
            jax.block_until_ready(out)
            samples[name]["wall"].append((time.perf_counter() - wall) / k)
            samples[name]["cpu"].append((time.process_time() - cpu) / k)
    return samples


def fitted_exponent(ns, costs) -> float:
    if len(ns) < 2:
        return float("nan")
    slope, _ = np.polyfit(np.log(np.asarray(ns, float)), np.log(np.asarray(costs, float)), 1)
    return float(slope)


def _first_line(name: str, n: int, row: dict, size: str = "N") -> str:
    return (
        f"  {size} = {n:3d} {name:34s} first result {row['first_s']:.2f} s wall, "
        f"{row['first_cpu_s']:.2f} s CPU (trace {row['trace']:.2f}, lower {row['lower']:.2f}, "
        f"XLA {row['xla']:.2f} s; import {row['import_s']:.2f} s)"
    )


def measure(
    part: str,
    contenders: tuple[str, ...],
    sizes: tuple[int, ...],
    repeats: int,
    check: Callable,
    size: str = "N",
) -> tuple[dict, dict, dict]:
    """Each size: every surviving contender's first result in a fresh process, then all of them
    compiled here and timed alternately. Returns ``(first, per_step, skipped)``: ``first[(name,
    n)]`` the fresh process's row (``None`` past ``CAP_S``), ``per_step[(name, n)]`` = (wall s, CPU s,
    half the interquartile range / median) per RK4 step, ``skipped[name]`` the first size left out.
    ``check(n, finals)`` prints the agreement of the final states (``finals[name]``)."""
    skipped: dict[str, int] = {}
    first: dict[tuple[str, int], dict | None] = {}
    per_step: dict[tuple[str, int], tuple[float, float, float]] = {}
    build = BUILDERS[part]
    for n in sizes:
        alive = [c for c in contenders if c not in skipped]
        for name in alive:
            row = fresh_first_result(name, n, part)
            first[(name, n)] = row
            if row is None:
                skipped[name] = n
                print(f"  {name} at {size} = {n}: no result within {CAP_S:.0f} s, skipped from here on")
            else:
                print(_first_line(name, n, row, size), flush=True)
        alive = [c for c in alive if c not in skipped]
        calls: dict[str, Callable[[], Any]] = {}
        for name in alive:
            solve, args = build(name, n)
            compiled = jax.jit(solve).lower(*args).compile()
            calls[name] = lambda compiled=compiled, args=args: compiled(*args)
        samples = timed_alternating(calls, repeats)
        finals = {
            name: jax.tree_util.tree_map(np.asarray, jax.block_until_ready(call()))
            for name, call in calls.items()
        }
        for name in alive:
            s = samples[name]
            wall, cpu = statistics.median(s["wall"]), statistics.median(s["cpu"])
            iqr = statistics.quantiles(s["wall"], n=4) if len(s["wall"]) >= 4 else [wall, wall, wall]
            per_step[(name, n)] = (wall / STEPS, cpu / STEPS, 0.5 * (iqr[2] - iqr[0]) / wall)
        check(n, finals)
        later = [m for m in sizes if m > n]
        for name in alive:
            predicted = per_step[(name, n)][0] * STEPS * (later[0] / n) ** 2.5 if later else 0.0
            if predicted > CALL_CAP_S:
                skipped[name] = later[0]
                print(
                    f"  {name}: one call predicted at {predicted:.0f} s at {size} = {later[0]}, "
                    "skipped from there"
                )
    return first, per_step, skipped


def _speedup_rows(sizes, first, per_step) -> list[list]:
    """Recursive against autodiff at each size: CPU per step, speedup, first result (CPU s)."""
    rows = []
    for n in sizes:
        fast, slow = per_step.get((RECURSIVE, n)), per_step.get((AUTODIFF, n))
        f_fast, f_slow = first.get((RECURSIVE, n)), first.get((AUTODIFF, n))
        rows.append(
            [
                n,
                fast[1] * 1e6 if fast else float("nan"),
                slow[1] * 1e6 if slow else float("nan"),
                slow[1] / fast[1] if fast and slow else float("nan"),
                f_fast["first_cpu_s"] if f_fast else float("nan"),
                f_slow["first_cpu_s"] if f_slow else float("nan"),
                f_slow["first_cpu_s"] / f_fast["first_cpu_s"] if f_fast and f_slow else float("nan"),
            ]
        )
    return rows


SPEEDUP_HEADER = [
    "N",
    "recursive CPU µs/step",
    "autodiff CPU µs/step",
    "x (autodiff/recursive)",
    "recursive first CPU s",
    "autodiff first CPU s",
    "x first",
]


def run_chain(repeats: int) -> list[str]:
    print(f"\n== Chain of N links: {STEPS} RK4 steps of dt = {DT}, fresh process per first result ==")

    def check(n: int, finals: dict[str, Any]) -> None:
        aba, dense = finals.get("ABA"), finals.get("CRBA + RNEA, dense solve")
        checks = []
        if aba is not None and dense is not None:
            checks.append(f"|ABA − dense| = {np.max(np.abs(aba[0] - dense[0])):.1e}")
        for name in (RECURSIVE, AUTODIFF):
            simulated = finals.get(name)
            if aba is not None and simulated is not None:
                checks.append(f"|ABA − {name}| = {np.max(np.abs(aba[0] - simulated)):.1e}")
        if RECURSIVE in finals and AUTODIFF in finals:
            checks.append(
                f"|recursive − autodiff| = {np.max(np.abs(finals[RECURSIVE] - finals[AUTODIFF])):.1e}"
            )
        print(f"  N = {n}: final q agree: {', '.join(checks)}", flush=True)

    first, per_step, skipped = measure("chain", CHAIN_CONTENDERS, SIZES, repeats, check)

    rows = []
    for name in CHAIN_CONTENDERS:
        for n in SIZES:
            key = (name, n)
            if key not in per_step:
                note = "skipped (call too long)" if name in skipped and n >= skipped[name] else "-"
                if key in first and first[key] is None:
                    note = f"first result > {CAP_S:.0f} s, skipped"
                rows.append([name, n, note, "", "", "", "", "", "", ""])
                continue
            wall, cpu, spread = per_step[key]
            base = per_step.get((BASELINE, n))
            f = first[key]
            assert f is not None
            rows.append(
                [
                    name,
                    n,
                    wall * 1e6,
                    cpu * 1e6,
                    spread * 100,
                    cpu / base[1] if base else float("nan"),
                    f["first_s"],
                    f["first_cpu_s"],
                    f["trace"] + f["lower"],
                    f["xla"],
                ]
            )
    common.print_table(
        f"Chain of N links, {STEPS} RK4 steps (µs per step: wall, CPU; ratio = CPU per step / hand M, solve; "
        "first result in a fresh process after the imports)",
        [
            "contender",
            "N",
            "µs/step",
            "CPU µs/step",
            "iqr ±%",
            "x hand (CPU)",
            "first s",
            "first CPU s",
            "trace+lower s",
            "XLA s",
        ],
        rows,
    )
    common.print_table(
        f"Chain: {RECURSIVE} (recursive) against {AUTODIFF}, same rounds (x = autodiff / recursive, CPU)",
        SPEEDUP_HEADER,
        _speedup_rows(SIZES, first, per_step),
    )
    exponents = []
    for name in CHAIN_CONTENDERS:
        ns = [n for n in SIZES if (name, n) in per_step]
        p_wall = fitted_exponent(ns, [per_step[(name, n)][0] for n in ns])
        p_cpu = fitted_exponent(ns, [per_step[(name, n)][1] for n in ns])
        big = [n for n in ns if n >= 50]
        p_big = fitted_exponent(big, [per_step[(name, n)][1] for n in big])
        exponents.append([name, ",".join(map(str, ns)) or "-", p_wall, p_cpu, p_big])
    common.print_table(
        "Fitted exponent p of per-step cost ∝ N^p (least squares on log-log)",
        ["contender", "N used", "p (wall)", "p (CPU)", "p (CPU, N ≥ 50)"],
        exponents,
    )
    verdicts = []
    for name in ("ABA", RECURSIVE, ARTICULATED, AUTODIFF):
        f = first.get((name, 100))
        if f is None:
            continue
        for label, key in (("first result", "first_s"), ("first result (CPU)", "first_cpu_s")):
            ok = f[key] <= FIRST_RESULT_TARGET_S
            verdicts.append(
                f"{'ok' if ok else 'MISS'}  {name} {label} at N = 100: {f[key]:.2f} s "
                f"(target ≤ {FIRST_RESULT_TARGET_S} s)"
            )
    for name in ("ABA", RECURSIVE, ARTICULATED, AUTODIFF):
        row = next((row for row in exponents if row[0] == name), None)
        if row is None:
            continue
        verdicts.append(
            f"{'ok' if row[3] <= 1.2 else 'MISS'}  {name} per step O(N) up to N = {SIZES[-1]}: "
            f"p = {row[3]:.2f} (CPU; {row[4]:.2f} over N ≥ 50)"
        )
    return verdicts


# ----------------------------------------------------------------------------- floating base
def run_floating(repeats: int) -> list[str]:
    print(
        f"\n== Floating base + two legs of K hinges: {STEPS} RK4 steps of dt = {DT}, "
        "fresh process per first result =="
    )
    agreement: dict[int, tuple[float, float, float]] = {}

    def check(k: int, finals: dict[str, Any]) -> None:
        if RECURSIVE not in finals or AUTODIFF not in finals:
            return
        (q_fast, qd_fast), (q_slow, qd_slow) = finals[RECURSIVE], finals[AUTODIFF]
        dq, dqd = float(np.max(np.abs(q_fast - q_slow))), float(np.max(np.abs(qd_fast - qd_slow)))
        unit = float(max(abs(np.linalg.norm(q[3:7]) - 1.0) for q in (q_fast, q_slow)))
        agreement[k] = (dq, dqd, unit)
        moved = float(np.max(np.abs(q_fast[:3] - np.array([0.0, 0.0, 1.0]))))
        print(
            f"  K = {k}: |q recursive − autodiff| = {dq:.1e}, |q̇ …| = {dqd:.1e}, "
            f"| |Q| − 1 | = {unit:.1e}, base moved {moved:.1e} m",
            flush=True,
        )

    first, per_step, skipped = measure("floating", FLOATING_CONTENDERS, FLOATING_SIZES, repeats, check, "K")
    rows = []
    for name in FLOATING_CONTENDERS:
        for k in FLOATING_SIZES:
            key = (name, k)
            if key not in per_step:
                note = f"first result > {CAP_S:.0f} s, skipped" if first.get(key, 0) is None else "skipped"
                rows.append([name, k, 7 + 2 * k, note, "", "", "", "", ""])
                continue
            wall, cpu, spread = per_step[key]
            f = first[key]
            assert f is not None
            rows.append(
                [
                    name,
                    k,
                    7 + 2 * k,
                    wall * 1e6,
                    cpu * 1e6,
                    spread * 100,
                    f["first_s"],
                    f["first_cpu_s"],
                    f["xla"],
                ]
            )
    common.print_table(
        f"Floating base, two legs of K hinges (nq = 7 + 2K), {STEPS} RK4 steps (µs per step: wall, CPU; "
        "first result in a fresh process after the imports)",
        ["contender", "K", "nq", "µs/step", "CPU µs/step", "iqr ±%", "first s", "first CPU s", "XLA s"],
        rows,
    )
    common.print_table(
        "Floating base: recursive against autodiff, same rounds (x = autodiff / recursive, CPU; N = K)",
        SPEEDUP_HEADER,
        _speedup_rows(FLOATING_SIZES, first, per_step),
    )
    common.print_table(
        "Final states, recursive against autodiff",
        ["K", "max |Δq|", "max |Δq̇|", "max | |Q| − 1 |"],
        [[k, f"{a:.1e}", f"{b:.1e}", f"{c:.1e}"] for k, (a, b, c) in agreement.items()],
    )
    exponents = []
    for name in FLOATING_CONTENDERS:
        ks = [k for k in FLOATING_SIZES if (name, k) in per_step]
        nq = [7 + 2 * k for k in ks]
        exponents.append(
            [name, ",".join(map(str, nq)) or "-", fitted_exponent(nq, [per_step[(name, k)][1] for k in ks])]
        )
    common.print_table(
        "Fitted exponent p of per-step CPU cost ∝ nq^p (least squares on log-log)",
        ["contender", "nq used", "p (CPU)"],
        exponents,
    )
    verdicts = []
    speedups = _speedup_rows(FLOATING_SIZES, first, per_step)
    verdicts.append(
        "info  floating base, autodiff / recursive CPU per step: "
        + ", ".join(f"K = {row[0]}: {row[3]:.1f}x" for row in speedups)
        + "; first result: "
        + ", ".join(f"{row[6]:.1f}x" for row in speedups)
    )
    if agreement:
        dq = max(a for a, _, _ in agreement.values())
        dqd = max(b for _, b, _ in agreement.values())
        unit = max(c for _, _, c in agreement.values())
        verdicts.append(
            f"{'ok' if dq <= 1e-10 and dqd <= 1e-9 else 'MISS'}  floating base, recursive against autodiff "
            f"after {STEPS} steps: max |Δq| = {dq:.1e} (target ≤ 1e-10), max |Δq̇| = {dqd:.1e} (≤ 1e-9), "
            f"max | |Q| − 1 | = {unit:.1e}"
        )
    del skipped
    return verdicts


# ----------------------------------------------------------------------------- batch
def run_batch(repeats: int) -> list[str]:
    mujoco: Any = importlib.import_module("mujoco")
    importlib.import_module("mujoco.rollout")

    import jaxlag as jl
    import jaxlag.robots as jlr

    print(f"\n== Batch of {BATCH} arms (7 DoF), {BATCH_STEPS} steps of dt = {DT}, one core ==")
    model = mujoco.MjModel.from_xml_string(ARM)
    model.opt.timestep = DT
    tree = jlr.load(ARM)
    nv = model.nv
    rng = np.random.default_rng(0)
    q0 = rng.uniform(-0.5, 0.5, (BATCH, nv))
    v0 = rng.uniform(-0.5, 0.5, (BATCH, nv))

    data = mujoco.MjData(model)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    size = mujoco.mj_stateSize(model, spec)
    initial = np.empty((BATCH, size))
    for b in range(BATCH):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = q0[b]
        data.qvel[:] = v0[b]
        mujoco.mj_getState(model, data, initial[b], spec)
    models = {}
    for label, integrator in (
        ("RK4", mujoco.mjtIntegrator.mjINT_RK4),
        ("Euler", mujoco.mjtIntegrator.mjINT_EULER),
    ):
        m = mujoco.MjModel.from_xml_string(ARM)
        m.opt.timestep = DT
        m.opt.integrator = integrator
        models[label] = m
    controls = np.zeros((BATCH, BATCH_STEPS, model.nu))
    out = {label: np.empty((BATCH, BATCH_STEPS, size)) for label in models}

    def mujoco_call(label):
        def call():
            mujoco.rollout.rollout(
                models[label], data, initial, controls, nstep=BATCH_STEPS, state=out[label]
            )
            return out[label]

        return call

    def aba(q, v):
        return jlr.forward_dynamics(tree, q, v)

    def dense(q, v):
        return jnp.linalg.solve(jlr.mass_matrix(tree, q), -tree.damping * v - jlr.bias_forces(tree, q, v))

    nu = tree.actuation.shape[1]
    system = jlr.system(tree).with_control(lambda q, qd: jnp.zeros(nu))  # zero controls, as MuJoCo's
    jq0, jv0 = jnp.asarray(q0), jnp.asarray(v0)
    programs = {
        "vmap(ABA), RK4": jax.vmap(lambda q, v: rk4_solve(aba, q, v, BATCH_STEPS)),
        "vmap(CRBA + RNEA, dense solve), RK4": jax.vmap(lambda q, v: rk4_solve(dense, q, v, BATCH_STEPS)),
        "simulate_batch(jlr.system), RK4": lambda q, v: (
            jl.simulate_batch(system, q, v, **simulate_kwargs(BATCH_STEPS)).q
        ),
    }
    calls: dict[str, Callable[[], Any]] = {
        "MuJoCo rollout, RK4": mujoco_call("RK4"),
        "MuJoCo rollout, Euler": mujoco_call("Euler"),
    }
    compile_s = {}
    for name, fn in programs.items():
        start = time.perf_counter()
        compiled = jax.jit(fn).lower(jq0, jv0).compile()
        compile_s[name] = time.perf_counter() - start
        calls[name] = lambda compiled=compiled: compiled(jq0, jv0)
    samples = timed_alternating(calls, repeats)

    mujoco_q = out["RK4"][:, -1, 1 : 1 + model.nq]  # FULLPHYSICS: time, qpos, qvel, ...
    moved = float(np.max(np.abs(mujoco_q - q0)))
    print(f"  |q(T) − q(0)| of MuJoCo RK4: {moved:.1e} (the scale of the agreement column)")
    agree = {
        name: float(np.max(np.abs(np.asarray(calls[name]())[0] - mujoco_q)))
        if name != "simulate_batch(jlr.system), RK4"
        else float(np.max(np.abs(np.asarray(calls[name]())[:, -1] - mujoco_q)))
        for name in programs
    }
    reference = "MuJoCo rollout, RK4"
    ref_wall = statistics.median(samples[reference]["wall"])
    ref_cpu = statistics.median(samples[reference]["cpu"])
    rows = []
    for name in calls:
        wall, cpu = statistics.median(samples[name]["wall"]), statistics.median(samples[name]["cpu"])
        rows.append(
            [
                name,
                BATCH * BATCH_STEPS / wall,
                BATCH * BATCH_STEPS / cpu,
                ref_wall / wall,
                ref_cpu / cpu,
                compile_s.get(name, float("nan")),
                f"{agree[name]:.1e}" if name in agree else "",
            ]
        )
    common.print_table(
        f"Batch of {BATCH} arms, {BATCH_STEPS} steps of {DT} s (state-steps/s; ratio = ours / MuJoCo RK4, "
        "same rounds, >1 is faster than MuJoCo)",
        [
            "contender",
            "state-steps/s",
            "per CPU s",
            "x MuJoCo (wall)",
            "x MuJoCo (CPU)",
            "compile s",
            "|q − MuJoCo RK4|",
        ],
        rows,
    )
    ratio = ref_cpu / statistics.median(samples["vmap(ABA), RK4"]["cpu"])
    return [f"info  vmap(ABA) RK4 / MuJoCo RK4 state-steps per CPU second: {ratio:.2f}x"]


_T_START = time.perf_counter()


def main() -> None:
    if len(sys.argv) >= 2 and sys.argv[1] == "--first":
        first_result_child(sys.argv[2], sys.argv[3], int(sys.argv[4]))
        return
    parts = sys.argv[1:] or ["chain", "batch", "floating"]
    print(common.environment_line())
    print(f"load: {os.getloadavg()}")
    verdicts = []
    if "chain" in parts:
        verdicts += run_chain(common.REPEATS)
    if "batch" in parts:
        verdicts += run_batch(common.REPEATS)
    if "floating" in parts:
        verdicts += run_floating(common.REPEATS)
    print()
    for line in verdicts:
        print(line)


if __name__ == "__main__":
    main()
