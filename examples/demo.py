"""jaxlag demo: a particle sliding off a sphere, its normal force, and g recovered by gradients.

A particle starts at rest near the top of a sphere of radius R. We keep the radial coordinate
r as a redundant coordinate and impose r = R as a holonomic constraint; the multiplier λ is the
normal force, λ = m g (3 cos θ − 2 cos θ₀). The particle would leave the sphere where λ = 0,
at cos θ = (2/3) cos θ₀ (arccos(2/3) ≈ 48.19° from rest at the very top).

Then, pretending the simulated angles are measurements, we recover g by gradient descent
through the whole constrained simulation with optax.

Run:  python examples/demo.py     (writes sphere_demo.png next to this file)
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

import jaxlag as jl

jax.config.update("jax_enable_x64", True)


def lagrangian(q, qd, args):
    r, theta = q  # θ measured from the top of the sphere
    rd, thetad = qd
    m, g = args["m"], args["g"]
    return 0.5 * m * (rd**2 + r**2 * thetad**2) - m * g * r * jnp.cos(theta)


def on_sphere(q, args):
    return jnp.array([q[0] - args["R"]])


def main():
    system = jl.System(lagrangian, holonomic=on_sphere)
    args = {"m": 1.0, "g": 9.81, "R": 2.0}
    theta0 = 0.01
    q0, qd0 = jnp.array([2.0, theta0]), jnp.array([0.0, 0.0])
    ts = jnp.linspace(0.0, 3.0, 601)

    traj = jl.simulate(system, q0, qd0, ts, args=args)
    theta = traj.q[:, 1]
    normal_force = traj.multipliers[:, 0]
    closed_form = args["m"] * args["g"] * (3 * jnp.cos(theta) - 2 * jnp.cos(theta0))
    print(f"steps taken: {int(traj.stats['num_steps'])}")
    print(f"max |λ − m g (3cos θ − 2cos θ0)|  = {float(jnp.max(jnp.abs(normal_force - closed_form))):.2e}")
    print(f"max |r − R| (constraint residual) = {float(jnp.max(jnp.abs(traj.q[:, 0] - 2.0))):.2e}")
    print(f"energy drift max |h − h0|        = {float(jnp.max(jnp.abs(traj.energy - traj.energy[0]))):.2e}")

    # The normal force changes sign between two save points: interpolate the crossing.
    i = int(np.argmax(np.asarray(normal_force) < 0))
    assert i > 0, "the particle did not reach the departure angle: simulate longer"
    a, b = float(normal_force[i - 1]), float(normal_force[i])
    theta_leave = float(theta[i - 1] + (theta[i] - theta[i - 1]) * a / (a - b))
    expected = float(np.arccos(2.0 / 3.0 * np.cos(theta0)))
    print(f"normal force vanishes at θ = {np.degrees(theta_leave):.4f}°"
          f" (closed form arccos(2/3 cos θ0) = {np.degrees(expected):.4f}°)")

    # --- recover g from the 'measured' angles (first 1.5 s, while still on the sphere) -------
    fit_ts = ts[ts <= 1.5]
    observed = jl.simulate(system, q0, qd0, fit_ts, args=args).q[:, 1]

    @jax.jit
    def loss(g):
        model = jl.simulate(system, q0, qd0, fit_ts, args={**args, "g": g})
        return jnp.mean((model.q[:, 1] - observed) ** 2)

    g = jnp.asarray(7.0)
    optimizer = optax.adam(0.3)
    state = optimizer.init(g)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    for step in range(150):
        value, grad = value_and_grad(g)
        updates, state = optimizer.update(grad, state)
        g = optax.apply_updates(g, updates)
        if step % 30 == 0:
            print(f"  fit step {step:3d}: g = {float(g):.6f}, loss = {float(value):.3e}")
    print(f"recovered g = {float(g):.6f} (true 9.81)")

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: skipping the plot (pip install 'jaxlag[examples]')")
        return
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    ax1.plot(ts, np.degrees(theta))
    ax1.axhline(np.degrees(expected), ls="--", c="k", label="arccos(2/3 cos θ0)")
    ax1.set(xlabel="t [s]", ylabel="θ [deg]", title="angle from the top")
    ax1.legend()
    ax2.plot(np.degrees(theta), normal_force, label="λ (jaxlag multiplier)")
    ax2.plot(np.degrees(theta), closed_form, "--", label="m g (3cos θ − 2cos θ0)")
    ax2.axhline(0.0, c="k", lw=0.5)
    ax2.set(xlabel="θ [deg]", ylabel="normal force [N]", title="constraint force")
    ax2.legend()
    fig.tight_layout()
    out = Path(__file__).with_name("sphere_demo.png")
    fig.savefig(out, dpi=100)
    print(f"plot written to {out}")


if __name__ == "__main__":
    main()
