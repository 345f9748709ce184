"""Recover g and l of a pendulum from noisy camera positions of its bob.

θ(t) alone depends only on g/l; the bob's Cartesian position l (sin θ, −cos θ) pins both.
Run:  python examples/fit_pendulum.py     (writes fit_pendulum.png next to this file)
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _plotting import plot_fit, report

import jaxlag as jl

jax.config.update("jax_enable_x64", True)


def pendulum(q, qd, args):
    return 0.5 * args["l"] ** 2 * qd[0] ** 2 + args["g"] * args["l"] * jnp.cos(q[0])


def bob(q, qd, args):
    return args["l"] * jnp.array([jnp.sin(q[0]), -jnp.cos(q[0])])


def main():
    system = jl.System(pendulum)
    true = {"g": 9.81, "l": 0.8}
    ts = jnp.linspace(0.0, 4.0, 81)
    q0, qd0 = jnp.array([0.9]), jnp.array([0.0])
    clean = jax.vmap(lambda q: bob(q, None, true))(jl.simulate(system, q0, qd0, ts, args=true).q)
    observed = clean + 0.01 * np.random.default_rng(1).standard_normal(clean.shape)

    result = jl.fit(
        system,
        {"g": 9.81 * 1.2, "l": 0.8 * 0.8},
        jl.Experiment(ts, observed, q0, qd0),
        observe=bob,
        transforms={"g": jl.Positive(), "l": jl.Positive()},
    )
    print(
        f"Levenberg–Marquardt: {result.num_steps} steps, residual std {float(result.residual_std):.4f}"
        " (noise 0.01)"
    )
    report(true, result)
    fitted = jax.vmap(lambda q: bob(q, None, result.params))(
        jl.simulate(system, q0, qd0, ts, args=result.params).q
    )
    plot_fit(
        Path(__file__).with_name("fit_pendulum.png"),
        ts,
        observed,
        fitted,
        result.loss_history,
        ["x", "y"],
        "pendulum bob: camera data vs fitted model",
    )


if __name__ == "__main__":
    main()
