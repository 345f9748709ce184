"""Ensemble throughput: one fused loop for the batch against vmap of diffrax, on any backend.

B double pendulums (unit masses and lengths, g = 9.81, absolute angles, the states of
``bench_batch``), Tsit5 at a constant step for every contender, ``SaveAt(t1=True)``; one compiled
call integrates the whole batch. Throughput: ``B × steps / (time of one call)``, state-steps/s.

Contenders (all in one process, same method, same steps, same initial states):

* jaxlag ``simulate_batch(method=jl.Ensemble(backend=...))`` with each backend present: ``"xla"``
  (one ``lax.scan`` over steps, state ``(B, n)``) everywhere, ``"pallas"`` (one fused kernel) on a
  GPU;
* jaxlag ``simulate_batch(method=jl.Vmap())`` (``jax.vmap`` of ``diffrax.diffeqsolve``);
* (a) the explicit closed-form θ̈₁, θ̈₂, ``jax.vmap`` of ``diffrax.diffeqsolve``;
* (b) the explicit formula in a bare ``lax.fori_loop`` over steps of the batched Tsit5 stages
  (written out here, no library code);
* (c) on a GPU, a hand-written Pallas kernel of the explicit formula: structure-of-arrays state,
  one program per block of 128 members, the whole integration in registers. On CPU it is only
  checked for correctness in Pallas's interpreter (B = 4), not timed.

CPU: B = 1, 64, 1024, 8192 (fewer steps for larger B, every call ~0.1 s). GPU: B = 1, 1024,
10⁵, 10⁶ at 100 steps (the issue's table). jaxlag runs with ``checks=jl.Checks(initial_state=False)``
(the baselines check nothing either).

Run: ``python -m benchmarks.bench_ensemble`` from the repository root.
"""

from __future__ import annotations

import warnings

import diffrax
import jax
import jax.numpy as jnp

import jaxlag as jl

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported
from .bench_batch import initial_states
from .bench_unconstrained import G, T, double_pendulum_explicit, double_pendulum_lagrangian, solve_hand

GPU = jax.default_backend() != "cpu"
if GPU:
    SIZES = ((1, 100), (1024, 100), (100_000, 100), (1_000_000, 100))
elif common.QUICK:
    SIZES = ((1, 200), (64, 100), (1024, 20))
else:
    SIZES = ((1, 1000), (64, 1000), (1024, 100), (8192, 25))
TABLEAU = diffrax.Tsit5().tableau
BLOCK = 128


def _stage_sum(y, h, coefficients, ks):
    total = None
    for c, k in zip(coefficients, ks):
        if c != 0:
            total = float(c) * k if total is None else total + float(c) * k
    return y if total is None else y + h * total


def _explicit_field(y):
    """``(θ, θ̇) ↦ (θ̇, θ̈)`` of the whole batch; ``y`` is (B, 4)."""
    qdd = jax.vmap(double_pendulum_explicit)(y[:, :2], y[:, 2:])
    return jnp.concatenate([y[:, 2:], qdd], axis=1)


def tsit5_step(field, y, h):
    """One Tsit5 step written out from the tableau (first-same-as-last not used: 7 stages would
    reuse one evaluation; every contender evaluates the same 6 distinct stages per step)."""
    ks = [field(y)]
    for a in TABLEAU.a_lower[:-1]:
        ks.append(field(_stage_sum(y, h, a, ks)))
    return _stage_sum(y, h, TABLEAU.b_sol[:-1], ks)


def bare_loop(nsteps):
    """(b) the hand formula, batched Tsit5 in one ``lax.fori_loop``: the XLA speed of light."""
    h = T / nsteps

    def run(q0, qd0):
        y = jnp.concatenate([q0, qd0], axis=1)
        y = jax.lax.fori_loop(0, nsteps, lambda i, y: tsit5_step(_explicit_field, y, h), y)
        return y[:, :2]

    return run


def _tuple_stage_sum(y, h, coefficients, ks):
    total = None
    for c, k in zip(coefficients, ks):
        if c != 0:
            term = tuple(float(c) * x for x in k)
            total = term if total is None else tuple(a + b for a, b in zip(total, term))
    return y if total is None else tuple(a + h * b for a, b in zip(y, total))


def pallas_kernel(nsteps, interpret=False):
    """(c) a hand-written Pallas kernel of the explicit formula.

    Structure of arrays in the simplest form a GPU lowering accepts: four 1-D arrays
    ``θ₁, θ₂, θ̇₁, θ̇₂`` of length B, one program per block of 128 members, elementwise arithmetic
    only (no transposes, concatenations or batched matrix ops), the whole integration in a
    ``fori_loop`` on values held in registers.
    """
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton  # float64: Triton (Mosaic GPU has no f64 loads)

    h = T / nsteps

    def field(y):  # double_pendulum_explicit, returning a tuple instead of a stacked array
        t1, t2, w1, w2 = y
        delta = t1 - t2
        s, c = jnp.sin(delta), jnp.cos(delta)
        den = 3.0 - jnp.cos(2.0 * delta)
        a1 = (-3.0 * G * jnp.sin(t1) - G * jnp.sin(t1 - 2.0 * t2) - 2.0 * s * (w2**2 + w1**2 * c)) / den
        a2 = 2.0 * s * (2.0 * w1**2 + 2.0 * G * jnp.cos(t1) + w2**2 * c) / den
        return (w1, w2, a1, a2)

    def step(y):
        ks = [field(y)]
        for a in TABLEAU.a_lower[:-1]:
            ks.append(field(_tuple_stage_sum(y, h, a, ks)))
        return _tuple_stage_sum(y, h, TABLEAU.b_sol[:-1], ks)

    def kernel(t1_ref, t2_ref, w1_ref, w2_ref, o1_ref, o2_ref):
        y = (t1_ref[...], t2_ref[...], w1_ref[...], w2_ref[...])
        y = jax.lax.fori_loop(0, nsteps, lambda i, y: step(y), y)
        o1_ref[...] = y[0]
        o2_ref[...] = y[1]

    def run(q0, qd0):
        batch = q0.shape[0]
        block = min(BLOCK, batch)
        pad = -batch % block
        columns = [jnp.pad(x[:, i], (0, pad), mode="edge") for x in (q0, qd0) for i in range(2)]
        spec = pl.BlockSpec((block,), lambda i: (i,))
        shape = jax.ShapeDtypeStruct(columns[0].shape, columns[0].dtype)
        o1, o2 = pl.pallas_call(
            kernel,
            out_shape=[shape, shape],
            grid=(columns[0].shape[0] // block,),
            in_specs=[spec] * 4,
            out_specs=[spec] * 2,
            interpret=interpret,
            compiler_params=triton.CompilerParams(num_warps=4),
        )(*columns)
        return jnp.stack([o1, o2], axis=1)[:batch]

    return run


def jaxlag_batch(system, nsteps, **kwargs):
    def run(q0, qd0):
        return jl.simulate_batch(
            system,
            q0,
            qd0,
            t0=0.0,
            t1=T,
            dt0=T / nsteps,
            saveat=diffrax.SaveAt(t1=True),
            solver=diffrax.Tsit5(),
            stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=nsteps + 1,
            checks=jl.Checks(initial_state=False),
            **kwargs,
        ).q[:, -1]

    return run


def _jaxlag_kernel_only(system, nsteps):
    """jaxlag's Pallas backend without its CPU fallback (to ask whether it lowers for CUDA)."""
    from jaxlag._batch.methods import BatchProblem
    from jaxlag.experimental._ensemble.run import ConstantGrid, EnsembleRun, run_impl
    from jaxlag.experimental._ensemble.settings import make_settings

    settings = make_settings(diffrax.Tsit5(), diffrax.ConstantStepSize(), nsteps, None, False)

    def run(q0, qd0):
        batch = q0.shape[0]
        ts = jnp.broadcast_to(jnp.array([0.0, T]), (batch, 2))
        grid = ConstantGrid(jnp.full((batch, 1), nsteps, jnp.int32), nsteps, True, True)
        problem = BatchProblem(system, q0, qd0, ts, None, None, batch, 0, None)
        ensemble = EnsembleRun(
            problem=problem,
            ts=ts,
            settings=settings,
            grid=grid,
            dt0=None,
            baumgarte=None,
            projection=None,
            check=False,
            tolerance=1e-8,
            keep_first=False,
        )
        return run_impl(ensemble, "pallas")[0].q  # (trajectory, initial-state diagnostics)

    return run


def explicit_vmap(nsteps):
    return jax.vmap(lambda q0, qd0: solve_hand(double_pendulum_explicit, q0, qd0, nsteps)[-1])


def lowers_for_cuda(fn, *args) -> str:
    """Whether ``fn`` lowers for CUDA (Pallas → Triton), checked by ``jax.export`` without a GPU."""
    from jax import export

    triton_call = export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")
    try:
        export.export(jax.jit(fn), platforms=["cuda"], disabled_checks=[triton_call])(*args)
    except Exception as error:  # noqa: BLE001 - reported, not raised
        return f"no ({type(error).__name__}: {str(error).splitlines()[0][:120]})"
    return "yes"


def run():
    system = jl.System(double_pendulum_lagrangian)
    if not GPU:  # the kernels' arithmetic in the interpreter, their GPU lowering by jax.export
        q0, qd0 = initial_states(4)
        error = common.max_abs_diff(pallas_kernel(50, interpret=True)(q0, qd0), bare_loop(50)(q0, qd0))
        print(f"hand Pallas kernel (interpret mode, B = 4, 50 steps) vs bare loop: max |Δq| = {error:.1e}")
        q0, qd0 = initial_states(256)
        print(
            "lowers for CUDA (Triton), float64: hand kernel:",
            lowers_for_cuda(pallas_kernel(10), q0, qd0),
            "| jaxlag Ensemble(backend='pallas'):",
            lowers_for_cuda(_jaxlag_kernel_only(system, 10), q0, qd0),
        )
    rows, errors = [], {}
    for batch, nsteps in SIZES:
        q0, qd0 = initial_states(batch)
        named = [
            ("jaxlag ensemble, xla", jaxlag_batch(system, nsteps, method=jl.Ensemble(backend="xla"))),
        ]
        if GPU:
            named.append(
                (
                    "jaxlag ensemble, pallas",
                    jaxlag_batch(system, nsteps, method=jl.Ensemble(backend="pallas")),
                )
            )
        named += [
            ("jaxlag simulate_batch (vmap)", jaxlag_batch(system, nsteps, method=jl.Vmap())),
            ("(a) hand formula, diffrax + vmap", explicit_vmap(nsteps)),
            ("(b) hand formula, bare lax loop", bare_loop(nsteps)),
        ]
        if GPU:
            named.append(("(c) hand formula, Pallas kernel", pallas_kernel(nsteps)))
        cs = []
        for name, fn in named:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                cs.append(common.compile_contender(name, fn, q0, qd0))
            if any("did not lower" in str(w.message) for w in caught):
                cs[-1].name = name + " (did not lower: XLA loop)"
                print(f"B={batch}: {caught[0].message}")
        common.time_alternating(cs, repeats=common.REPEATS if batch <= 64 else max(3, common.REPEATS // 2))
        reference = cs[-1 if not GPU else -2].compiled(q0, qd0)  # the bare loop
        errors[batch] = max(common.max_abs_diff(c.compiled(q0, qd0), reference) for c in cs)
        vmap_time = next(c.median for c in cs if "simulate_batch" in c.name)
        loop_time = next(c.median for c in cs if "bare lax loop" in c.name)
        for c in cs:
            rows.append(
                [
                    batch,
                    nsteps,
                    c.name,
                    batch * nsteps / c.median / 1e6,
                    vmap_time / c.median,
                    c.median / loop_time,
                    c.compile_s,
                    100 * common.spread(c),
                ]
            )
    common.print_table(
        f"Ensemble throughput ({jax.default_backend()}): double pendulum, Tsit5, constant steps, "
        "SaveAt(t1=True), one compiled call per batch",
        [
            "B",
            "steps",
            "contender",
            "M state-steps/s",
            "speed-up vs simulate_batch",
            "x(b) time",
            "compile s",
            "iqr ±%",
        ],
        rows,
    )
    print(
        "\nagreement with (b), max |Δq(T)| over the batch: "
        + ", ".join(f"B={k}: {v:.1e}" for k, v in errors.items())
    )
    return []


if __name__ == "__main__":
    print(common.environment_line())
    run()
