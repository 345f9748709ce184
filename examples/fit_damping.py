"""Recover the damping coefficient (and stiffness) of an oscillator from noisy positions.

Rayleigh dissipation R = ½ c q̇² enters as the generalized force −∂R/∂q̇.
Run:  python examples/fit_damping.py     (writes fit_damping.png next to this file)
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _plotting import plot_fit, report

import jaxlag as jl

jax.config.update("jax_enable_x64", True)


def spring(q, qd, args):
    return 0.5 * qd[0] ** 2 - 0.5 * args["k"] * q[0] ** 2


def rayleigh(q, qd, args):
    return 0.5 * args["c"] * qd[0] ** 2


def main():
    system = jl.System(spring, dissipation=rayleigh)
    true = {"k": 4.0, "c": 0.35}
    ts = jnp.linspace(0.0, 10.0, 101)
    q0, qd0 = jnp.array([1.0]), jnp.array([0.0])
    clean = jl.simulate(system, q0, qd0, ts, args=true).q
    observed = clean + 0.01 * np.random.default_rng(3).standard_normal(clean.shape)

    result = jl.fit(
        system,
        {"k": 3.0, "c": 0.1},
        jl.Experiment(ts, observed, q0, qd0),
        transforms={"k": jl.Positive(), "c": jl.Positive()},
    )
    print(f"Levenberg–Marquardt: {result.num_steps} steps")
    report(true, result)
    fitted = jl.simulate(system, q0, qd0, ts, args=result.params).q
    plot_fit(
        Path(__file__).with_name("fit_damping.png"),
        ts,
        observed,
        fitted,
        result.loss_history,
        ["q"],
        "damped oscillator: data vs fitted model",
    )


if __name__ == "__main__":
    main()
