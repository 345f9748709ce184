"""Learned Lagrangians: plain LNN vs DeLaN vs constrained LNN (CLNN) on chain pendulums.

Data: the ready models ``jl.systems.double_pendulum()`` and ``jl.systems.n_link_pendulum(3)``
(unit masses and rods, g = 9.81). Training trajectories of 2 s sampled every 0.05 s (41 states
each) from θ ~ U(−1, 1) rad, θ̇ ~ U(−1, 1) rad/s, with the true accelerations; the same training
set (10, 30 or 100 trajectories, per seed) for every model. 16 held-out trajectories of 4 s from
the same distribution.

Models (``jaxlag.learned``), all MLPs of width 64 and depth 2 with softplus:

* LNN: ``MLPLagrangian`` of (cos θ, sin θ, θ̇);
* DeLaN: ``DeLaN`` with the same angle embedding (M = C Cᵀ positive definite);
* CLNN: ``ConstrainedLagrangian`` in the Cartesian positions of the bobs, learned masses and
  potential, the known rod constraints ``|x_k − x_{k−1}| = 1`` imposed by the KKT solve.

Training: the library's recipe, ``jll.Recipe()`` (compared with a plain recipe, adam(1e-3) on
raw targets, by ``--recipes``): the coordinates of the accelerations balanced by their standard
deviations in the training set (``σ / rms(σ)``), minibatches of 256 states, adam with a warm-up
and cosine decay (peak 3e-3), gradient clipping, then a short multiple-shooting fine-tune
(segments of 5 samples = 0.2 s, RK4 at the sample step) at 3e-4; ``jll.train`` skips a step whose
gradient is not finite. ``fit`` runs the two ``jll.train`` calls of ``jll.train_recipe`` with the
recipe's losses and optimizers, drawing the minibatches of the second phase with
``PRNGKey(seed + 1)``.

``--hand-written`` trains ``jll.DeLaN`` and ``jll.ConstrainedLagrangian`` next to the same forms
written by hand through ``jl.System`` on a user's setting (8 trajectories of 101 samples, width
128, depth 3, clipped adam with a cosine decay from 1e-3, BENCH_HAND_STEPS full-batch steps) and
writes its section of RESULTS_learned.md (about 1.5 h on this shared machine at 2000 steps; the rows
are saved in BENCH_HAND_ROWS: BENCH_HAND_ONLY=name:targets,... reruns some contenders and keeps the
others, ``--hand-written --report`` rebuilds the section).

Metric: held-out rollouts (``jl.simulate_batch``, Tsit5, rtol 1e-7, atol 1e-9) from the true
initial states; error = RMS over the bobs of the Euclidean position error of each bob, in metres
(rods of 1 m), at t = 1, 2 and 4 s; the median over held-out trajectories × seeds is quoted. A
rollout that is not finite at that time (blown up, indefinite learned M, solver failure) is
*failed*: counted in the table, left out of the median. Training time: wall-clock of both phases
on one pinned core, compilation included (the first size of each model pays it).

Run: ``python -m benchmarks.bench_learned`` from the repository root (about 25 min on one core;
BENCH_QUICK=1 for a smoke test; BENCH_SIZES, BENCH_SEEDS, BENCH_LINKS, BENCH_STEPS,
BENCH_SHOOTING_STEPS change the grid). Writes benchmarks/RESULTS_learned.md and
docs/images/learned_benchmark.png; ``--report`` rebuilds both from the runs saved in BENCH_ROWS;
``--recipes`` compares a plain recipe (adam(1e-3), raw targets, full batch) with these defaults
(about 15 min; writes benchmarks/RESULTS_learned_recipes.md).
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxlag as jl
from jaxlag import learned as jll

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported

QUICK = common.QUICK
SIZES = (4, 8) if QUICK else tuple(int(s) for s in os.environ.get("BENCH_SIZES", "10,30,100").split(","))
SEEDS = (0,) if QUICK else tuple(range(int(os.environ.get("BENCH_SEEDS", "2"))))
LINKS = (2,) if QUICK else tuple(int(s) for s in os.environ.get("BENCH_LINKS", "2,3").split(","))
STEPS = 100 if QUICK else int(os.environ.get("BENCH_STEPS", "2000"))
SHOOTING_STEPS = 20 if QUICK else int(os.environ.get("BENCH_SHOOTING_STEPS", "200"))
WIDTH = 64
DEPTH = 2
BATCH = 256
SEGMENT = 5
SHOOTING_BATCH = 100
HELD_OUT = 4 if QUICK else 16
DT = 0.05
T_TRAIN = 2.0
T_TEST = 4.0
REPORT_TIMES = (1.0, 2.0, 4.0)
MODELS = ("LNN", "DeLaN", "CLNN")
ROOT = Path(__file__).resolve().parent.parent
#: Every finished run is saved here, so that `--report` can rebuild the table from a partial run.
ROWS = Path(os.environ.get("BENCH_ROWS", Path(tempfile.gettempdir()) / "jaxlag_bench_learned_rows.json"))


def true_system(links):
    if links == 2:
        return jl.systems.double_pendulum(), jl.systems.double_pendulum("cartesian")
    return jl.systems.n_link_pendulum(links), jl.systems.n_link_pendulum(links, "cartesian")


def positions(theta):
    """Bob positions (…, links, 2) of a unit-rod chain at absolute angles θ (from the downward vertical)."""
    steps = jnp.stack([jnp.sin(theta), -jnp.cos(theta)], axis=-1)
    return jnp.cumsum(steps, axis=-2)


def to_cartesian(theta, omega):
    x, xd = jax.jvp(positions, (theta,), (omega,))
    lead = theta.shape[:-1]
    return x.reshape(lead + (-1,)), xd.reshape(lead + (-1,))


def rods(x):
    """The known constraints of the Cartesian chain: ``f_k = |x_k − x_{k−1}| − 1``."""
    points = x.reshape(-1, 2)
    previous = jnp.concatenate([jnp.zeros((1, 2), x.dtype), points[:-1]])
    return jnp.sqrt(jnp.sum((points - previous) ** 2, axis=-1)) - 1.0


def make_models(kind, links, key):
    embedding = jll.AngleEmbedding(tuple(range(links)))
    if kind == "LNN":
        return jll.MLPLagrangian(links, WIDTH, DEPTH, key=key, embedding=embedding)
    if kind == "DeLaN":
        return jll.DeLaN(links, WIDTH, DEPTH, key=key, embedding=embedding)
    return jll.ConstrainedLagrangian(links, 2, rods, WIDTH, DEPTH, key=key)


def cartesian_data(data: jll.TrajectoryData) -> jll.TrajectoryData:
    x, xd = to_cartesian(data.q, data.qd)
    return jll.TrajectoryData(data.ts, x, xd)


def library_recipe() -> jll.Recipe:
    """The library's recipe at this run's step counts (its defaults: 2000 + 200 steps)."""
    return jll.Recipe(
        steps=STEPS,
        shooting_steps=SHOOTING_STEPS,
        batch_size=BATCH,
        segment_length=SEGMENT,
        shooting_batch_size=SHOOTING_BATCH,
    )


#: The plain recipe: adam(1e-3) on the raw accelerations, full batch, no
#: multiple-shooting phase (the same step count, STEPS).
ISSUE_OPTIMIZER = optax.adam(1e-3)


def fit(kind, links, train_angles, true_cartesian, true_angles, seed, recipe="defaults"):
    """Both phases (``recipe="plain"``: adam(1e-3), raw targets, full batch); returns the trained model,
    the seconds and the failed-member counts."""
    key = jax.random.PRNGKey(1000 + seed)
    model = make_models(kind, links, key)
    if kind == "CLNN":
        data = cartesian_data(train_angles)
        states = jll.state_data(true_cartesian, data)
    else:
        data = train_angles
        states = jll.state_data(true_angles, data)
    defaults = library_recipe()
    if recipe == "plain":
        loss, first, batch = jll.AccelerationLoss(), ISSUE_OPTIMIZER, None
    else:
        loss, first, batch = defaults.loss(states), defaults.optimizer(), min(BATCH, states.q.shape[0])
    start = time.perf_counter()
    result = jll.train(
        model,
        loss,
        states,
        optimizer=first,
        steps=STEPS,
        batch_size=batch,
        key=jax.random.PRNGKey(seed),
    )
    model = result.model
    accel_failed = int(result.failed[-min(100, len(result.failed)) :].sum())
    if SHOOTING_STEPS and recipe != "plain":
        pieces = jll.segments(data, SEGMENT)
        result = jll.train(
            model,
            defaults.shooting_loss(data),
            pieces,
            optimizer=defaults.shooting_optimizer(),
            steps=SHOOTING_STEPS,
            batch_size=min(SHOOTING_BATCH, pieces.q.shape[0]),
            key=jax.random.PRNGKey(seed + 1),
        )
        shoot_failed = int(result.failed.sum())
        model = result.model
    else:
        shoot_failed = 0
    return model, time.perf_counter() - start, accel_failed, shoot_failed


def rollout_errors(kind, model, test_angles):
    """Position error (metres, RMS over bobs) at every test time, NaN where the rollout failed."""
    q0, qd0 = test_angles.q[:, 0], test_angles.qd[:, 0]
    ts = test_angles.ts[0]
    if kind == "CLNN":
        q0, qd0 = to_cartesian(q0, qd0)
    traj = jl.simulate_batch(
        model.system(),
        q0,
        qd0,
        ts,
        stepsize_controller=diffrax.PIDController(rtol=1e-7, atol=1e-9),
        max_steps=20_000,
        throw=False,
        checks=jl.Checks(initial_state=False, times=False),
    )
    if kind == "CLNN":
        predicted = traj.q.reshape(traj.q.shape[:-1] + (-1, 2))
    else:
        predicted = positions(traj.q)
    truth = positions(test_angles.q)
    error = jnp.sqrt(jnp.mean(jnp.sum((predicted - truth) ** 2, axis=-1), axis=-1))
    finite = jnp.all(jnp.isfinite(traj.q), axis=-1)
    return np.asarray(jnp.where(finite, error, jnp.nan)), ts


def angular_accelerations(kind, model, test_angles):
    """Held-out θ̈ (states, links) predicted by the model; NaN rows where its solve failed.

    The CLNN predicts Cartesian ẍ; on a rod of unit length with direction (u, v) = (sin θ, −cos θ)
    the angle's acceleration is θ̈ = −v Δẍ + u Δÿ (Δ: this bob minus the previous one), since the
    θ̇² terms of the rod's acceleration are along the rod.
    """
    links = test_angles.q.shape[-1]
    theta, omega = test_angles.q.reshape(-1, links), test_angles.qd.reshape(-1, links)
    if kind != "CLNN":
        return jax.vmap(lambda a, b: jll.accelerations(model, a, b))(theta, omega)
    x, xd = to_cartesian(theta, omega)
    xdd = jax.vmap(lambda a, b: jll.accelerations(model, a, b))(x, xd).reshape(-1, links, 2)
    relative = xdd - jnp.concatenate([jnp.zeros_like(xdd[:, :1]), xdd[:, :-1]], axis=1)
    u, v = jnp.sin(theta), -jnp.cos(theta)
    return -v * relative[..., 0] + u * relative[..., 1]


def zero_model_error(test_angles):
    """Error of predicting the initial positions forever (a scale for the table)."""
    truth = positions(test_angles.q)
    return np.asarray(jnp.sqrt(jnp.mean(jnp.sum((truth - truth[:, :1]) ** 2, axis=-1), axis=-1)))


def main():
    rows = []
    started = time.perf_counter()
    for links in LINKS:
        angles, cartesian = true_system(links)
        for seed in SEEDS:
            key = jax.random.PRNGKey(seed)
            k_train, k_test = jax.random.split(key)
            pool = trajectories_for(angles, links, k_train, max(SIZES), T_TRAIN)
            test = trajectories_for(angles, links, k_test, HELD_OUT, T_TEST)
            baseline = zero_model_error(test)
            true_accelerations = jll.state_data(angles, test).qdd
            for size in SIZES:
                train_angles = jax.tree.map(lambda x: x[:size], pool)
                for kind in MODELS:
                    model, seconds, accel_failed, shoot_failed = fit(
                        kind, links, train_angles, cartesian, angles, seed
                    )
                    errors, ts = rollout_errors(kind, model, test)
                    predicted = angular_accelerations(kind, model, test)
                    accel_ok = np.all(np.isfinite(np.asarray(predicted)), axis=1)
                    difference = np.asarray(predicted) - np.asarray(true_accelerations)
                    accel_rms = float(np.sqrt(np.mean(difference[accel_ok] ** 2)))
                    row = {
                        "links": links,
                        "seed": seed,
                        "size": size,
                        "model": kind,
                        "train_s": seconds,
                        "accel_failed_last100": accel_failed,
                        "shooting_failed": shoot_failed,
                        "errors": errors.tolist(),
                        "ts": np.asarray(ts).tolist(),
                        "baseline": baseline.tolist(),
                        "accel_rms": accel_rms,
                        "accel_failed": int(np.sum(~accel_ok)),
                        "accel_states": int(accel_ok.shape[0]),
                        "accel_zero_rms": float(np.sqrt(np.mean(np.asarray(true_accelerations) ** 2))),
                    }
                    rows.append(row)
                    at = [float(np.nanmedian(errors[:, _index(ts, t)])) for t in REPORT_TIMES]
                    fails = int(np.sum(~np.isfinite(errors[:, -1])))
                    print(
                        f"[{time.perf_counter() - started:7.1f}s] {links}-link seed {seed} "
                        f"N={size:3d} {kind:5s} train {seconds:6.1f}s  err@1,2,4s "
                        + " ".join(f"{e:.3g}" for e in at)
                        + f"  failed {fails}/{errors.shape[0]}  θ̈ RMS {accel_rms:.3g}",
                        flush=True,
                    )
                    ROWS.write_text(json.dumps(rows))
    write_report(rows)


# ------------------------------------------------------------------ library models vs hand-written
HAND_TRAJECTORIES = 4 if QUICK else 8
HAND_SAMPLES = 11 if QUICK else 101  # every DT: 5 s
HAND_WIDTH, HAND_DEPTH = 128, 3
HAND_STEPS = 20 if QUICK else int(os.environ.get("BENCH_HAND_STEPS", "2000"))
#: Where `compare_hand_written` writes its section of RESULTS_learned.md (kept by `write_report`).
HAND_BEGIN, HAND_END = "<!-- hand-written: begin -->", "<!-- hand-written: end -->"


class HandDeLaN(eqx.Module):
    """A DeLaN as one writes it by hand: ``L = ½ q̇ᵀ C Cᵀ q̇ − V``, ``C`` lower triangular with a
    softplus diagonal, both from MLPs of ``(cos θ, sin θ)``; simulated through ``jl.System(L)``."""

    factor_net: eqx.nn.MLP
    potential_net: eqx.nn.MLP

    def __init__(self, key):
        k1, k2 = jax.random.split(key)
        self.factor_net = eqx.nn.MLP(4, 3, HAND_WIDTH, HAND_DEPTH, jax.nn.softplus, key=k1)
        self.potential_net = eqx.nn.MLP(4, "scalar", HAND_WIDTH, HAND_DEPTH, jax.nn.softplus, key=k2)

    def __call__(self, q, qd):
        features = jnp.concatenate([jnp.cos(q), jnp.sin(q)])
        out = self.factor_net(features)
        diagonal = jax.nn.softplus(out[:2]) + 1e-3
        factor = jnp.array([[diagonal[0], 0.0], [out[2], diagonal[1]]])
        v = factor.T @ qd
        return 0.5 * v @ v - self.potential_net(features)


class HandConstrained(eqx.Module):
    """A constrained Lagrangian as one writes it by hand: ``L = ½ Σ m_b |ẋ_b|² − V(x)`` with
    ``m_b = exp(μ_b)`` (1 at the start) and an MLP ``V``; ``jl.System(L, holonomic=rods)``."""

    log_masses: jax.Array
    potential_net: eqx.nn.MLP

    def __init__(self, key):
        self.log_masses = jnp.zeros(2)
        self.potential_net = eqx.nn.MLP(4, "scalar", HAND_WIDTH, HAND_DEPTH, jax.nn.softplus, key=key)

    def __call__(self, x, xd):
        return 0.5 * jnp.sum(jnp.repeat(jnp.exp(self.log_masses), 2) * xd**2) - self.potential_net(x)


#: (name, form, targets): the model and the acceleration targets it is trained on. ``library``:
#: `jll.Recipe().loss(states)`; ``scaled``: every coordinate divided by its standard deviation
#: (what the library did before, the cookbook's ``AccelerationLoss(scale=qdd.std(axis=0))``);
#: ``raw``: ``jll.AccelerationLoss()``, the plain mean squared error.
HAND_CONTENDERS = (
    ("jll.DeLaN", "DeLaN", "scaled"),
    ("jll.DeLaN", "DeLaN", "library"),
    ("jll.DeLaN", "DeLaN", "raw"),
    ("hand-written DeLaN", "DeLaN", "raw"),
    ("jll.ConstrainedLagrangian", "CLNN", "scaled"),
    ("jll.ConstrainedLagrangian", "CLNN", "library"),
    ("jll.ConstrainedLagrangian", "CLNN", "raw"),
    ("hand-written constrained", "CLNN", "raw"),
    ("hand-written constrained", "CLNN", "scaled"),
)
#: The rows of `compare_hand_written`, saved after every run, so that BENCH_HAND_ONLY (a
#: comma-separated list of ``name:targets``) can rerun some contenders and keep the others' rows
#: (of the same HAND_STEPS), and ``--hand-written --report`` can rebuild the section.
HAND_ROWS = Path(
    os.environ.get("BENCH_HAND_ROWS", Path(tempfile.gettempdir()) / "jaxlag_bench_learned_hand_rows.json")
)
HAND_ONLY = tuple(c for c in os.environ.get("BENCH_HAND_ONLY", "").split(",") if c)


def hand_model(name, key):
    if name == "jll.DeLaN":
        return jll.DeLaN(2, HAND_WIDTH, HAND_DEPTH, key=key, embedding=jll.AngleEmbedding((0, 1)))
    if name == "jll.ConstrainedLagrangian":
        return jll.ConstrainedLagrangian(2, 2, rods, HAND_WIDTH, HAND_DEPTH, key=key)
    if name == "hand-written DeLaN":
        return jl.System(HandDeLaN(key))
    return jl.System(HandConstrained(key), holonomic=rods)


def hand_loss(targets, states):
    if targets == "library":
        return jll.Recipe().loss(states)
    if targets == "scaled":
        return jll.AccelerationLoss(scale=jnp.std(states.qdd, axis=0))
    return jll.AccelerationLoss()


def compare_hand_written():
    """The library's DeLaN and constrained Lagrangian against hand-written ones through ``jl.System``.

    A user's setting: double pendulum, HAND_TRAJECTORIES trajectories of HAND_SAMPLES samples
    every DT, MLPs of width 128 and depth 3, adam with its gradient clipped to norm 1 and a
    cosine decay from 1e-3, HAND_STEPS full-batch steps; θ̈ RMS on the held-out trajectories of
    `main`. Every contender starts from the same key; the pairs differ in the model and in the
    acceleration targets (HAND_CONTENDERS). Writes its section of RESULTS_learned.md.
    BENCH_HAND_ONLY runs only the contenders it names and keeps the other rows saved in HAND_ROWS.
    """
    contenders = [c for c in HAND_CONTENDERS if not HAND_ONLY or f"{c[0]}:{c[2]}" in HAND_ONLY]
    unknown = set(HAND_ONLY) - {f"{c[0]}:{c[2]}" for c in HAND_CONTENDERS}
    if unknown:
        raise SystemExit(f"BENCH_HAND_ONLY: no contender {sorted(unknown)}")
    optimizer = optax.chain(
        optax.clip_by_global_norm(1.0), optax.adam(optax.cosine_decay_schedule(1e-3, HAND_STEPS))
    )
    angles, cartesian = true_system(2)
    rows = []
    started = time.perf_counter()
    for seed in SEEDS:
        k_train, k_test = jax.random.split(jax.random.PRNGKey(seed))
        pool = trajectories_for(angles, 2, k_train, HAND_TRAJECTORIES, (HAND_SAMPLES - 1) * DT)
        test = trajectories_for(angles, 2, k_test, HELD_OUT, T_TEST)
        true_accelerations = np.asarray(jll.state_data(angles, test).qdd)
        for name, form, targets in contenders:
            data = cartesian_data(pool) if form == "CLNN" else pool
            states = jll.state_data(cartesian if form == "CLNN" else angles, data)
            model = hand_model(name, jax.random.PRNGKey(1000 + seed))
            start = time.perf_counter()
            result = jll.train(
                model, hand_loss(targets, states), states, optimizer=optimizer, steps=HAND_STEPS
            )
            seconds = time.perf_counter() - start
            predicted = np.asarray(angular_accelerations(form, result.model, test))
            ok = np.all(np.isfinite(predicted), axis=1)
            rms = float(np.sqrt(np.mean((predicted[ok] - true_accelerations[ok]) ** 2)))
            rows.append(
                {
                    "seed": seed,
                    "name": name,
                    "targets": targets,
                    "steps": HAND_STEPS,
                    "rms": rms,
                    "failed": int(np.sum(~ok)),
                }
            )
            if not QUICK:
                _save_hand_rows(rows)
            print(
                f"[{time.perf_counter() - started:7.1f}s] seed {seed} {name:26s} {targets:8s} "
                f"θ̈ RMS {rms:.4g} failed {int(np.sum(~ok))} train {seconds:.0f}s",
                flush=True,
            )
    write_hand_written_report(_save_hand_rows(rows) if not QUICK else rows)


def _save_hand_rows(rows):
    """Merge ``rows`` into those saved in HAND_ROWS (replacing the same seed and contender, dropping
    rows of another HAND_STEPS) and save; returns the merged rows."""
    saved = json.loads(HAND_ROWS.read_text()) if HAND_ROWS.exists() else []
    done = {(r["seed"], r["name"], r["targets"]) for r in rows}
    kept = [
        r for r in saved if r.get("steps") == HAND_STEPS and (r["seed"], r["name"], r["targets"]) not in done
    ]
    merged = kept + list(rows)
    HAND_ROWS.write_text(json.dumps(merged))
    return merged


def write_hand_written_report(rows):
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        HAND_BEGIN,
        "## Library models against hand-written ones (`python -m benchmarks.bench_learned --hand-written`)",
        "",
        f"{date}; {_cpu_name()}, one pinned core; jax {jax.__version__}, float64. Double pendulum, "
        f"{HAND_TRAJECTORIES} trajectories of {HAND_SAMPLES} samples every {DT} s (θ, θ̇ ~ U(−1, 1)), MLPs of "
        f"width {HAND_WIDTH} and depth {HAND_DEPTH}, adam with the gradient clipped to norm 1 and a cosine "
        f"decay from 1e-3, {HAND_STEPS} full-batch steps, the same initial key for every contender. θ̈ RMS "
        f"(rad/s²) on the {HELD_OUT} held-out 4 s trajectories of each seed. Targets: *scaled*, every "
        "coordinate divided by its standard deviation (the library's advice before); *library*, "
        "`jll.Recipe().loss(states)`; *raw*, `jll.AccelerationLoss()`. A library model and the "
        "hand-written one of its form compute the same function from the same initial weights: on "
        "the same targets they differ only by floating-point rounding, grown through the training.",
        "",
        "| model | targets | " + " | ".join(f"seed {seed}" for seed in SEEDS) + " |",
        "|---|---|" + "---|" * len(SEEDS),
    ]
    missing = [
        f"seed {seed} {name}:{targets}"
        for name, _, targets in HAND_CONTENDERS
        for seed in SEEDS
        if not any(r["seed"] == seed and r["name"] == name and r["targets"] == targets for r in rows)
    ]
    if missing:
        print(f"not writing RESULTS_learned.md: no rows (of {HAND_STEPS} steps) for {', '.join(missing)}")
        return
    for name, _, targets in HAND_CONTENDERS:
        cells = []
        for seed in SEEDS:
            row = next(r for r in rows if r["seed"] == seed and r["name"] == name and r["targets"] == targets)
            cells.append(f"{row['rms']:.3g}" + (f" ({row['failed']} failed)" if row["failed"] else ""))
        lines.append(f"| {name} | {targets} | " + " | ".join(cells) + " |")
    lines.append(HAND_END)
    section = "\n".join(lines) + "\n"
    print(section)
    if QUICK:
        return
    path = ROOT / "benchmarks" / "RESULTS_learned.md"
    path.write_text(_without_hand_written(path.read_text()).rstrip("\n") + "\n\n" + section)


def _without_hand_written(text):
    if HAND_BEGIN not in text:
        return text
    return text[: text.index(HAND_BEGIN)] + text[text.index(HAND_END) + len(HAND_END) :].lstrip("\n")


RECIPE_SIZES = (2, 8, 32)


def compare_recipes():
    """A plain recipe against the defaults above, on the same data, models and initial weights.

    A first attempt's setting (double pendulum, 2, 8 and 32 training trajectories, width 64,
    depth 2, STEPS acceleration steps, 16 held-out trajectories, θ̈ RMS) with its recipe (adam(1e-3)
    on the raw accelerations, full batch) and with this benchmark's defaults, for every seed.
    Writes benchmarks/RESULTS_learned_recipes.md.
    """
    rows = []
    started = time.perf_counter()
    links = 2
    angles, cartesian = true_system(links)
    sizes = (2, 4) if QUICK else RECIPE_SIZES
    for seed in SEEDS:
        k_train, k_test = jax.random.split(jax.random.PRNGKey(seed))
        pool = trajectories_for(angles, links, k_train, max(sizes), T_TRAIN)
        test = trajectories_for(angles, links, k_test, HELD_OUT, T_TEST)
        true_accelerations = np.asarray(jll.state_data(angles, test).qdd)
        for size in sizes:
            train_angles = jax.tree.map(lambda x: x[:size], pool)
            for recipe in ("plain", "defaults"):
                for kind in MODELS:
                    model, seconds, _, _ = fit(kind, links, train_angles, cartesian, angles, seed, recipe)
                    errors, ts = rollout_errors(kind, model, test)
                    predicted = np.asarray(angular_accelerations(kind, model, test))
                    ok = np.all(np.isfinite(predicted), axis=1)
                    accel_rms = float(np.sqrt(np.mean((predicted[ok] - true_accelerations[ok]) ** 2)))
                    row = {
                        "seed": seed,
                        "size": size,
                        "recipe": recipe,
                        "model": kind,
                        "train_s": seconds,
                        "accel_rms": accel_rms,
                        "accel_failed": int(np.sum(~ok)),
                        "zero_rms": float(np.sqrt(np.mean(true_accelerations**2))),
                        "errors": [float(np.nanmedian(errors[:, _index(ts, t)])) for t in REPORT_TIMES],
                        "rollouts_failed": int(np.sum(~np.isfinite(errors[:, -1]))),
                        "rollouts": int(errors.shape[0]),
                    }
                    rows.append(row)
                    print(
                        f"[{time.perf_counter() - started:7.1f}s] seed {seed} N={size:2d} {recipe:8s} "
                        f"{kind:5s} θ̈ RMS {accel_rms:.3g} err@1,2,4s "
                        + " ".join(f"{e:.3g}" for e in row["errors"])
                        + f" failed {row['rollouts_failed']}/{row['rollouts']} train {seconds:.1f}s",
                        flush=True,
                    )
    write_recipes_report(rows)


def write_recipes_report(rows):
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        "# Learned Lagrangians: a plain training recipe against the defaults",
        "",
        f"{date}; {_cpu_name()}, one pinned core; jax {jax.__version__}, float64. "
        f"`python -m benchmarks.bench_learned --recipes`.",
        "",
        f"Double pendulum, the data of `bench_learned.py` (θ, θ̇ ~ U(−1, 1), 2 s at 0.05 s), {len(SEEDS)} "
        f"seeds, {HELD_OUT} held-out 4 s trajectories per seed, the same models (width {WIDTH}, depth "
        f"{DEPTH}) and the same initial weights for both recipes. *plain*: adam(1e-3) on the raw "
        f"accelerations, full batch, {STEPS} steps. *defaults*: `jll.Recipe()`, balanced accelerations, "
        f"minibatches of {BATCH}, warm-up + cosine adam (peak 3e-3) with clipping, {STEPS} steps, then "
        f"{SHOOTING_STEPS} multiple-shooting steps. θ̈ RMS in rad/s² over all held-out states "
        "(RMS over seeds); rollout error in metres, median over held-out trajectories × seeds; "
        "failed: rollouts not finite at 4 s.",
        "",
        "| trajectories | model | recipe | θ̈ RMS | error @ 1 s | error @ 2 s | error @ 4 s | failed "
        "| train s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    groups = {}
    for row in rows:
        groups.setdefault((row["size"], MODELS.index(row["model"]), row["recipe"] != "plain"), []).append(row)
    for (size, kind_index, _), group in sorted(groups.items()):
        accel = _rms([r["accel_rms"] for r in group])
        errors = np.asarray([r["errors"] for r in group])
        cells = " | ".join(
            f"{np.nanmedian(errors[:, j]):.3g}" if np.any(np.isfinite(errors[:, j])) else "—"
            for j in range(len(REPORT_TIMES))
        )
        failed = sum(r["rollouts_failed"] for r in group)
        total = sum(r["rollouts"] for r in group)
        seconds = float(np.mean([r["train_s"] for r in group]))
        accel_text = "—" if accel is None else f"{accel:.3g}"
        lines.append(
            f"| {size} | {MODELS[kind_index]} | {group[0]['recipe']} | {accel_text} | {cells} | "
            f"{failed}/{total} | {seconds:.0f} |"
        )
    zero = _rms([r["zero_rms"] for r in rows])
    lines.append(f"| — | zero | — | {zero:.3g} | — | — | — | — | — |")
    text = "\n".join(lines) + "\n"
    out = Path(tempfile.gettempdir()) if QUICK else ROOT / "benchmarks"
    (out / "RESULTS_learned_recipes.md").write_text(text)
    print(text)


def trajectories_for(system, links, key, count, duration):
    k1, k2 = jax.random.split(key)
    q0 = jax.random.uniform(k1, (count, links), minval=-1.0, maxval=1.0)
    qd0 = jax.random.uniform(k2, (count, links), minval=-1.0, maxval=1.0)
    ts = jnp.arange(int(round(duration / DT)) + 1) * DT
    traj = jl.simulate_batch(system, q0, qd0, ts)
    return jll.TrajectoryData(jnp.broadcast_to(ts, (count, ts.shape[0])), traj.q, traj.qd)


def _index(ts, t):
    return int(np.argmin(np.abs(np.asarray(ts) - t)))


def _cpu_name():
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _rms(values):
    """RMS of the finite values (a seed whose every state failed has none); None if there are none."""
    finite = [v for v in values if np.isfinite(v)]
    return float(np.sqrt(np.mean(np.square(finite)))) if finite else None


def summarize(rows):
    """(links, size, model) -> medians at the report times, failures, mean training seconds."""
    table = {}
    for row in rows:
        key = (row["links"], row["size"], row["model"])
        table.setdefault(key, []).append(row)
    out = {}
    for key, group in sorted(table.items(), key=lambda kv: (kv[0][0], kv[0][1], MODELS.index(kv[0][2]))):
        errors = np.concatenate([np.asarray(r["errors"]) for r in group])
        baseline = np.concatenate([np.asarray(r["baseline"]) for r in group])
        ts = group[0]["ts"]
        cells = []
        for t in REPORT_TIMES:
            column = errors[:, _index(ts, t)]
            cells.append(
                (
                    float(np.nanmedian(column)) if np.any(np.isfinite(column)) else float("nan"),
                    int(np.sum(~np.isfinite(column))),
                    float(np.median(baseline[:, _index(ts, t)])),
                )
            )
        seconds = [r["train_s"] for r in group]
        accel = [r for r in group if "accel_rms" in r]
        out[key] = {
            "cells": cells,
            "total": errors.shape[0],
            "seconds": seconds,
            # RMS over seeds of the per-seed RMS (the seeds have equally many held-out states).
            "accel_rms": _rms([r["accel_rms"] for r in accel]),
            "accel_failed": sum(r["accel_failed"] for r in accel),
            "accel_zero": _rms([r["accel_zero_rms"] for r in accel]),
        }
    return out


def write_report(rows):
    summary = summarize(rows)
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    machine = f"{_cpu_name()}, one pinned core (of {os.cpu_count()}, shared with other work)"
    lines = [
        "# Learned Lagrangians: data efficiency (benchmarks/bench_learned.py)",
        "",
        f"{date}; {machine}; jax {jax.__version__}, float64, Python {sys.version.split()[0]}.",
        f"Seeds: {len(SEEDS)}; {HELD_OUT} held-out 4 s trajectories per seed; acceleration phase "
        f"{STEPS} steps (minibatch {BATCH}), multiple-shooting phase {SHOOTING_STEPS} steps "
        f"(segments of {SEGMENT} samples, minibatch {SHOOTING_BATCH}); MLPs of width {WIDTH}, depth {DEPTH}.",
        "",
        "Held-out rollout error: RMS over the bobs of the Euclidean position error, in metres (rods of "
        "1 m), median over held-out trajectories × seeds; `(k failed)`: rollouts not finite at that "
        "time, left out of the median. `still` is the error of predicting the initial positions "
        "forever. θ̈ RMS: held-out angular accelerations at every state of the held-out trajectories, "
        "rad/s², RMS over states, coordinates and seeds (the metric of a first baseline); `zero` predicts "
        "θ̈ = 0. Training time: mean seconds per run on one core, both phases, compilation included "
        "(the first size of each model and chain pays it, ~20–60 s on this machine).",
        "",
        "| chain | trajectories | model | error @ 1 s | error @ 2 s | error @ 4 s | θ̈ RMS | train s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (links, size, kind), entry in summary.items():
        cells = []
        for median, failed, _ in entry["cells"]:
            text = f"{median:.3g}" if np.isfinite(median) else "—"
            if failed:
                text += f" ({failed} failed)"
            cells.append(text)
        name = {2: "double", 3: "triple"}.get(links, f"{links}-link")
        seconds = float(np.mean(entry["seconds"]))
        accel = "—" if entry["accel_rms"] is None else f"{entry['accel_rms']:.3g}"
        if entry["accel_failed"]:
            accel += f" ({entry['accel_failed']} states failed)"
        lines.append(f"| {name} | {size} | {kind} | " + " | ".join(cells) + f" | {accel} | {seconds:.0f} |")
    still = {}
    for (links, _size, _kind), entry in summary.items():
        still[links] = ([c[2] for c in entry["cells"]], entry["accel_zero"])
    for links, (values, zero) in still.items():
        name = {2: "double", 3: "triple"}.get(links, f"{links}-link")
        zero_text = "—" if zero is None else f"{zero:.3g}"
        cells = " | ".join(f"{v:.3g}" for v in values)
        lines.append(f"| {name} | — | still / zero | {cells} | {zero_text} | — |")
    text = "\n".join(lines) + "\n"
    out = Path(tempfile.gettempdir()) if QUICK else ROOT / "benchmarks"
    previous = out / "RESULTS_learned.md"
    if previous.exists() and HAND_BEGIN in previous.read_text():  # keep the hand-written comparison
        old = previous.read_text()
        text += "\n" + old[old.index(HAND_BEGIN) : old.index(HAND_END) + len(HAND_END)] + "\n"
    previous.write_text(text)
    print(text)
    plot(summary)


def plot(summary):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    links_all = sorted({k[0] for k in summary})
    fig, axes = plt.subplots(1, len(links_all), figsize=(5.2 * len(links_all), 4.4), squeeze=False)
    colors = {"LNN": "tab:red", "DeLaN": "tab:blue", "CLNN": "tab:green"}
    for ax, links in zip(axes[0], links_all):
        for kind in MODELS:
            keys = sorted(k for k in summary if k[0] == links and k[2] == kind)
            if not keys:
                continue
            sizes = [k[1] for k in keys]
            for j, style in zip(range(len(REPORT_TIMES)), ("-", "--", ":")):
                values = [summary[k]["cells"][j][0] for k in keys]
                label = f"{kind} @ {REPORT_TIMES[j]:g} s"
                ax.plot(sizes, values, style, marker="o", color=colors[kind], label=label)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xticks(sorted({k[1] for k in summary}))
        ax.set_xticklabels([str(s) for s in sorted({k[1] for k in summary})])
        ax.minorticks_off()
        ax.set_xlabel("training trajectories")
        ax.set_ylabel("held-out position error [m] (median)")
        ax.set_title({2: "double pendulum", 3: "triple pendulum"}.get(links, f"{links}-link chain"))
        ax.grid(True, which="both", alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, ncol=3, loc="lower center")
    fig.tight_layout(rect=(0.0, 0.14, 1.0, 1.0))
    path = (Path(tempfile.gettempdir()) if QUICK else ROOT / "docs" / "images") / "learned_benchmark.png"
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


if __name__ == "__main__":
    if "--hand-written" in sys.argv and "--report" in sys.argv:  # rebuild from HAND_ROWS
        write_hand_written_report(
            [r for r in json.loads(HAND_ROWS.read_text()) if r.get("steps") == HAND_STEPS]
        )
    elif "--report" in sys.argv:  # rebuild the table and the plot from the saved runs
        write_report(json.loads(ROWS.read_text()))
    elif "--recipes" in sys.argv:  # a plain recipe against the defaults
        compare_recipes()
    elif "--hand-written" in sys.argv:  # the library's models against hand-written ones
        compare_hand_written()
    else:
        main()
