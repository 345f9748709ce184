"""Constrained variational integration (RATTLE) vs the explicit KKT path: cost and crossover.

Two questions, both on float64 and one pinned core (``common``):

**A. Cost per step.** Every contender takes ``NSTEPS`` fixed steps from the same state,
``SaveAt``/``save_every`` only the final state, compiled ahead of time, timed alternately:

* ``KKT Tsit5 + Projection()``: ``jl.simulate`` as a user gets it for a constrained system
  (index-1 KKT right-hand side, Tsit5, ``ConstantStepSize``, the default projection onto
  ``f = 0``, ``ḟ = 0`` after every step) — the reference of the ratios;
* ``KKT Tsit5, projection=None``: the raw index-1 equations (constraints drift);
* ``KKT midpoint RK2 + Projection()``: an explicit Runge–Kutta method of RATTLE's order;
* ``RATTLE``: ``simulate_variational`` (explicit positions, Newton on the m multipliers only);
* ``RATTLE order 4``: its symmetric triple-jump composition (3 RATTLE substeps per step);
* ``variational midpoint``: ``method="variational"``, the general path (Newton in q and λ,
  as for any ``L(q, q̇)``).

Systems: a Cartesian pendulum (n = 2, m = 1) and the planar Cartesian N-link chain of
``bench_constrained`` (n = 2N, m = N; N = 2 is the double pendulum). No initial-state check.

**B. Equal accuracy over a long horizon.** Accuracy is the largest relative energy error
``max_{t ≤ T} |E(t) − E(0)| / |E(0)|`` (the constraints hold to ≤ 1e-12 for all contenders: the
KKT path projects, RATTLE solves them). Each method runs on a grid of step sizes to ``T_MAX``
(in chunks that restart from the last state; energies sampled every few steps), giving
``err(h, T)`` for every horizon ``T ≤ T_MAX`` from one run per ``h``. For a target ``ε`` and
horizon ``T`` the step a method needs is read off a power-law fit ``err ≈ a h^p`` on its grid,
and its cost is ``T / h × (µs/step from A)``. RATTLE's error is bounded (``a`` independent of
``T``); Tsit5's drifts linearly, ``err ≈ a T h^p``, so it needs ever smaller steps and the
costs cross at

    T* = ε / (a_RK · h*^p_RK),   h* = h_VI(ε) · c_RK / c_VI,

reported per ``ε`` (measured when ``T* ≤ T_MAX``, else extrapolated with the fitted drift law).
Systems: the Cartesian pendulum released at θ₀ = 2 rad (regular) and the double pendulum
released at (1, 2) rad with (0.5, −0.3) rad/s (chaotic).

Run: ``python -m benchmarks.bench_variational`` from the repository root (≈ 2–3 minutes;
``BENCH_QUICK=1`` ≈ 40 s).
"""

from __future__ import annotations

import math
import time

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import jaxlag as jl
from jaxlag._variational import simulate_variational

from . import bench_constrained as bc
from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported

G = 9.81
NSTEPS = 200 if common.QUICK else 1000
DT = 1e-3
CHAIN_SIZES = (2,) if common.QUICK else (2, 5, 10)
CHUNK = 5000  # steps per restart in part B
EVERY = 5  # energy sampled every EVERY steps
HORIZONS = (10.0, 100.0, 1000.0)


# ----------------------------------------------------------------------------- systems
def pendulum_lagrangian(q, qd):
    return 0.5 * jnp.sum(qd**2) - G * q[1]


def rod(q):
    return jnp.array([jnp.sqrt(q[0] ** 2 + q[1] ** 2) - 1.0])


def pendulum():
    q0 = jnp.array([math.sin(2.0), -math.cos(2.0)])
    return jl.System(pendulum_lagrangian, holonomic=rod), q0, jnp.zeros(2)


def chain(n):
    return jl.System(bc.lagrangian, holonomic=bc.distance_constraints), *bc.initial_state(n)


def chaotic_double_pendulum():
    th1, th2, w1, w2 = 1.0, 2.0, 0.5, -0.3
    q0 = jnp.array(
        [math.sin(th1), -math.cos(th1), math.sin(th1) + math.sin(th2), -math.cos(th1) - math.cos(th2)]
    )
    qd0 = jnp.array(
        [
            w1 * math.cos(th1),
            w1 * math.sin(th1),
            w1 * math.cos(th1) + w2 * math.cos(th2),
            w1 * math.sin(th1) + w2 * math.sin(th2),
        ]
    )
    return jl.System(bc.lagrangian, holonomic=bc.distance_constraints), q0, qd0


# ----------------------------------------------------------------------------- contenders
def kkt(system, solver=None, projection=jl.Projection()):
    solver = diffrax.Tsit5() if solver is None else solver

    def run(q0, qd0, dt=DT, nsteps=NSTEPS, ts=None):
        saveat = diffrax.SaveAt(t1=True) if ts is None else diffrax.SaveAt(ts=ts)
        traj = jl.simulate(
            system,
            q0,
            qd0,
            t0=0.0,
            t1=nsteps * dt,
            dt0=dt,
            saveat=saveat,
            solver=solver,
            stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=nsteps + 1,
            projection=projection,
            checks=jl.Checks(initial_state=False),
        )
        return traj

    return run


def variational(system, **kwargs):
    def run(q0, qd0, dt=DT, nsteps=NSTEPS, every=None):
        return simulate_variational(
            system,
            q0,
            qd0,
            dt=dt,
            num_steps=nsteps,
            save_every=nsteps if every is None else every,
            checks=jl.Checks(initial_state=False),
            **kwargs,
        )

    return run


def contenders(system, full):
    out = [("KKT Tsit5 + Projection()", kkt(system)), ("RATTLE", variational(system))]
    if full:
        out += [
            ("KKT Tsit5, projection=None", kkt(system, projection=None)),
            ("KKT midpoint RK2 + Projection()", kkt(system, diffrax.Midpoint())),
            ("RATTLE order 4 (3 substeps)", variational(system, order=4)),
            ("variational midpoint (general)", variational(system, method="variational")),
        ]
    return out


# ----------------------------------------------------------------------------- part A
def cost_per_step():
    """µs/step of every contender; returns {(system, contender): µs/step}."""
    rows, costs = [], {}
    cases = [("pendulum", 2, 1, *pendulum())]
    cases += [(f"chain N={n}", 2 * n, n, *chain(n)) for n in CHAIN_SIZES]
    for name, n, m, system, q0, qd0 in cases:
        full = name in ("pendulum", "chain N=2")
        cs = [
            common.compile_contender(label, lambda a, b, fn=fn: fn(a, b).q[-1], q0, qd0)
            for label, fn in contenders(system, full)
        ]
        common.time_alternating(cs)
        ref = cs[0]
        final = {c.name: c.compiled(*c.args) for c in cs}
        for c in cs:
            us = c.median / NSTEPS * 1e6
            costs[(name, c.name)] = us
            rows.append(
                [
                    name,
                    n,
                    m,
                    c.name,
                    us,
                    c.median / ref.median,
                    common.max_abs_diff(final[c.name], final[ref.name]),
                    c.compile_s,
                    100 * common.spread(c),
                ]
            )
    common.print_table(
        f"A. Cost per step: {NSTEPS} fixed steps of h = {DT}, final state only; "
        "ratio against the KKT path with projection (Tsit5)",
        ["system", "n", "m", "contender", "µs/step", "x(KKT)", "|Δq(T)| vs KKT", "compile s", "iqr ±%"],
        rows,
    )
    return costs


# ----------------------------------------------------------------------------- part B
def energy_error_run(make_chunk, system, q0, qd0, h, horizon):
    """Times and running max of the relative energy error along one run to ``horizon``."""
    e0 = float(system.energy(q0, qd0))
    chunks = max(1, int(round(horizon / (CHUNK * h))))
    q, qd = q0, qd0
    errors, worst_f = [], 0.0
    for _ in range(chunks):
        qs, qds, energies, f = make_chunk(q, qd, h)
        errors.append(np.abs(np.asarray(energies)[1:] - e0) / abs(e0))
        worst_f = max(worst_f, float(f))
        q, qd = qs[-1], qds[-1]
    err = np.concatenate(errors)
    t = h * EVERY * np.arange(1, err.size + 1)
    return t, np.fmax.accumulate(err), worst_f


def chunk_kkt(system, solver):
    ts = jnp.arange(CHUNK // EVERY + 1, dtype=jnp.float64)
    run = kkt(system, solver)

    @jax.jit
    def chunk(q, qd, h):
        traj = run(q, qd, dt=h, nsteps=CHUNK, ts=ts * EVERY * h)
        f = jnp.max(jnp.abs(traj.constraint_residuals[0]))
        return traj.q, traj.qd, traj.energy, f

    return chunk


def chunk_variational(system, **kwargs):
    run = variational(system, **kwargs)

    @jax.jit
    def chunk(q, qd, h):
        traj = run(q, qd, dt=h, nsteps=CHUNK, every=EVERY)
        f = jnp.max(jnp.abs(traj.constraint_residuals[0]))
        return traj.q, traj.qd, traj.energy, f

    return chunk


def power_law(hs, errs):
    """Least-squares fit ``log err = log a + p log h``; returns ``(a, p)``."""
    p, log_a = np.polyfit(np.log(hs), np.log(errs), 1)
    return math.exp(log_a), p


def accuracy_and_crossover(costs):
    scale = 0.1 if common.QUICK else 1.0
    problems = [
        (
            "pendulum",
            "pendulum",
            pendulum,
            2000.0 * scale,
            {
                "KKT Tsit5 + Projection()": (
                    chunk_kkt,
                    dict(solver=diffrax.Tsit5()),
                    (0.08, 0.04, 0.02, 0.01),
                ),
                "RATTLE": (chunk_variational, {}, (0.02, 0.01, 0.005, 0.0025)),
                "RATTLE order 4 (3 substeps)": (chunk_variational, dict(order=4), (0.04, 0.02, 0.01, 0.005)),
            },
        ),
        (
            "double pendulum (chaotic)",
            "chain N=2",
            chaotic_double_pendulum,
            1000.0 * scale,
            {
                "KKT Tsit5 + Projection()": (
                    chunk_kkt,
                    dict(solver=diffrax.Tsit5()),
                    (0.04, 0.02, 0.01, 0.005),
                ),
                "RATTLE": (chunk_variational, {}, (0.01, 0.005, 0.0025, 0.00125)),
                "RATTLE order 4 (3 substeps)": (
                    chunk_variational,
                    dict(order=4),
                    (0.02, 0.01, 0.005, 0.0025),
                ),
            },
        ),
    ]
    for title, cost_key, make, t_max, methods in problems:
        system, q0, qd0 = make()
        horizons = [T for T in HORIZONS if T < t_max] + [t_max]
        table, fits = [], {}
        start = time.perf_counter()
        for label, (factory, kwargs, grid) in methods.items():
            chunk = factory(system, **kwargs)
            at_horizon = {T: [] for T in horizons}
            for h in grid:
                t, err, f = energy_error_run(chunk, system, q0, qd0, h, t_max)
                row = [label, f"{h:g}", f"{int(round(t_max / h)):,}"]
                for T in horizons:
                    e = float(err[np.searchsorted(t, T, side="right") - 1])
                    at_horizon[T].append(e)
                    row.append(f"{e:.1e}")
                table.append(row + [f"{f:.0e}"])
            fits[label] = {T: power_law(grid, at_horizon[T]) for T in horizons}
            fits[label]["grid"] = grid
        common.print_table(
            f"B. {title}: max relative energy error up to T (one run per h to T = {t_max:g}, "
            f"sampled every {EVERY} steps; {time.perf_counter() - start:.0f} s)",
            ["method", "h", "steps"] + [f"T={T:g}" for T in horizons] + ["max|f|"],
            table,
        )
        crossover(title, cost_key, fits, horizons, costs)


def crossover(title, cost_key, fits, horizons, costs):
    """Cost to reach ε at each horizon, and the crossover horizon T* per ε."""
    rk = "KKT Tsit5 + Projection()"
    c_rk = costs[(cost_key, rk)]
    rows, notes = [], []
    t_max = horizons[-1]
    a_rk, p_rk = fits[rk][t_max]
    a_rk /= t_max  # linear drift: err ≈ a_rk · T · h^p
    for eps in (1e-3, 1e-4, 1e-5, 1e-6):
        for T in horizons:
            row = [f"{eps:.0e}", f"{T:g}"]
            best = {}
            for label in fits:
                a, p = fits[label][T]
                h = (eps / a) ** (1.0 / p)
                grid = fits[label]["grid"]
                flag = "" if min(grid) / 2 <= h <= 2 * max(grid) else "*"
                cost_ms = T / h * costs[(cost_key, label)] * 1e-3
                best[label] = cost_ms
                row += [f"{h:.2g}{flag}", f"{cost_ms:.3g}"]
            vi = min(best[k] for k in best if k != rk)
            row.append(f"{vi / best[rk]:.2g}")
            rows.append(row)
        # Crossover with the cheaper RATTLE variant for this ε (bounded error: T-independent).
        candidates = []
        for label in fits:
            if label == rk:
                continue
            a, p = fits[label][t_max]
            h_vi = (eps / a) ** (1.0 / p)
            h_star = h_vi * c_rk / costs[(cost_key, label)]
            candidates.append((eps / (a_rk * h_star**p_rk), label, h_vi))
        t_star, label, h_vi = min(candidates)
        where = "measured range" if t_star <= t_max else "extrapolated"
        notes.append(
            f"  ε = {eps:.0e}: {label} (h = {h_vi:.2g}) is cheaper than KKT Tsit5 for "
            f"T > T* ≈ {t_star:.2g} ({where})"
        )
    header = ["ε", "T"]
    for label in fits:
        header += [f"h {label}", "ms"]
    header.append("RATTLE best / KKT")
    common.print_table(
        f"B. {title}: step needed for max energy error ≤ ε up to T (fit err ≈ a h^p per T; "
        "* = outside the measured h grid) and the cost T/h × µs/step",
        header,
        rows,
    )
    print(f"drift law of KKT Tsit5: err ≈ {a_rk:.3g} · T · h^{p_rk:.2f}; crossover horizons:")
    print("\n".join(notes))


def run():
    costs = cost_per_step()
    accuracy_and_crossover(costs)


if __name__ == "__main__":
    print(common.environment_line())
    start = time.perf_counter()
    run()
    print(f"\ntotal wall time {time.perf_counter() - start:.0f} s")
