"""Impacts: 1,000 bouncing balls in one vmapped call, jaxlag vs a hand-written diffrax loop.

A ball on a floor, ``L = ½ż² − g z``, ``z ≥ 0``, restitution ``e`` from 0.6 to 0.9 across the
batch, dropped from ``h = 1``, simulated for 3 s with 31 save times (a few bounces for
``e = 0.9``; ``e = 0.6`` comes to rest, by the Zeno rule, after 12).

Contenders (Tsit5, ``PIDController(1e-10, 1e-10)``, 24 segments, compiled ahead of time,
``jax.vmap`` over the 1,000 members):

* hand loop: ``lax.scan`` of 24 ``diffrax.diffeqsolve`` segments of ``(ż, v̇) = (v, −g)``, each
  ended by a ``diffrax.Event`` on ``z`` (Newton root find, 1e-13) and restarted with
  ``v → −e v`` (plastic, and the ball at rest, once the rebound would fly less than
  ``τ = 3 ms``, the rule of ``jl.Events``' ``zeno_time``); the saves of each segment kept. The
  reference.
* jaxlag: ``System(L, floor, unilateral=jl.Unilateral(0, restitution=e))`` and ``simulate``
  with ``jl.Events(max_segments=24, zeno_time=τ)`` (the same rule; the default ends the bouncing
  later, at a rebound below the constraint tolerance): the KKT impulse, the event log, the
  impulses, the multipliers' sign checks and the projections that the hand loop does not do.

Run: ``python -m benchmarks.bench_impacts`` from the repository root.
"""

from __future__ import annotations

import diffrax
import jax
import jax.numpy as jnp
import optimistix as optx

import jaxlag as jl

from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported

G, H, SPAN = 9.81, 1.0, 3.0
SEGMENTS = 24
BATCH = 100 if common.QUICK else 1000
TS = jnp.linspace(0.0, SPAN, 31)
TAU = 1e-3 * SPAN  # the Zeno rule of both contenders: jaxlag's zeno_time, given


def lagrangian(q, qd):
    return 0.5 * qd[0] ** 2 - G * q[0]


def floor(q):
    return q[:1]


def with_jaxlag(e):
    system = jl.System(lagrangian, floor, unilateral=jl.Unilateral(0, restitution=e))
    traj = jl.simulate(
        system, jnp.array([H]), jnp.zeros(1), TS, events=jl.Events(max_segments=SEGMENTS, zeno_time=TAU)
    )
    return traj.q[:, 0]


def hand(e):
    """The bouncing ball by hand: segments of free flight, an event at z = 0, v → −e v."""
    term = diffrax.ODETerm(lambda t, y, args: jnp.stack([y[1], -G]))
    solver = diffrax.Tsit5()
    controller = diffrax.PIDController(rtol=1e-10, atol=1e-10)
    root_finder = optx.Newton(rtol=1e-13, atol=1e-13)

    def segment(carry, _):
        t_s, y, resting, out, filled = carry
        # After a bounce z starts at 0 going up: z/(t − t_s) has only the landing as a root.
        event = diffrax.Event(
            lambda t, y, args, **kw: jnp.where(t > t_s, y[0] / jnp.where(t > t_s, t - t_s, 1.0), 1.0),
            root_finder=root_finder,
            direction=False,
        )
        sol = diffrax.diffeqsolve(
            term,
            solver,
            t_s,
            SPAN,
            None,
            y,
            saveat=diffrax.SaveAt(
                subs=[diffrax.SubSaveAt(ts=jnp.clip(TS, t_s, SPAN)), diffrax.SubSaveAt(t1=True)]
            ),
            stepsize_controller=controller,
            event=event,
            max_steps=4096,
        )
        saved, (t_e,), (y_e,) = sol.ys[0], sol.ts[1], sol.ys[1]
        take = (TS >= t_s) & (TS <= t_e) & ~filled & ~resting
        out = jnp.where(take, saved[:, 0], out)
        filled = filled | take
        hit = t_e < SPAN
        v = y_e[1]
        rest = hit & (2.0 * e * jnp.abs(v) < G * TAU)  # the rebound would fly less than τ
        y_next = jnp.where(rest, jnp.zeros(2), jnp.stack([0.0, -e * v]))
        done = resting | ~hit | rest
        return (jnp.where(done, SPAN, t_e), y_next, done, out, filled), None

    carry0 = (
        jnp.asarray(0.0),
        jnp.array([H, 0.0]),
        jnp.asarray(False),
        jnp.zeros_like(TS),
        jnp.zeros(TS.shape, bool),
    )
    (_, _, _, out, filled), _ = jax.lax.scan(segment, carry0, None, length=SEGMENTS)
    return jnp.where(filled, out, 0.0)  # not filled: at rest on the floor


def main() -> None:
    es = jnp.linspace(0.6, 0.9, BATCH)
    contenders = [
        common.compile_contender("hand diffrax loop", jax.vmap(hand), es),
        common.compile_contender("jaxlag Unilateral(e)", jax.vmap(with_jaxlag), es),
    ]
    diff = common.max_abs_diff(contenders[0].compiled(es), contenders[1].compiled(es))
    rounds = 3 if common.QUICK else 5  # the median of 5 (not the environment's default rounds)
    common.time_alternating(contenders, repeats=rounds)
    base = contenders[0].median
    rows = [[c.name, c.median * 1e3, c.median / base, common.spread(c), c.compile_s] for c in contenders]
    common.print_table(
        f"{BATCH} bouncing balls, one vmapped call (CPU, one core, median of {rounds} rounds, "
        f"compile excluded); max |z_hand − z_jaxlag| = {diff:.1e}",
        ["contender", "ms/call", "ratio", "spread", "compile s"],
        rows,
    )


if __name__ == "__main__":
    print(common.environment_line())
    main()
