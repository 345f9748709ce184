"""jaxlag demo: a particle sliding off a sphere — motion, normal force, release, and g and R
recovered from noisy camera data.

1. Simulate. A particle starts at rest near the top of a sphere of radius R. The radial coordinate
   r is kept and r − R ≥ 0 imposed as a *unilateral* constraint: its multiplier λ is the normal
   force, λ = m g (3 cos θ − 2 cos θ₀), and the particle leaves the sphere when λ reaches zero, at
   cos θ = (2/3) cos θ₀ (arccos(2/3) ≈ 48.19° from rest at the very top). jaxlag finds that
   instant with an event and continues with free flight.
2. Fit. From noisy camera positions (x, y) of the particle while it is on the sphere, recover g
   and R with Levenberg–Marquardt through the constrained simulation, with standard errors.

Run:  python examples/demo.py     (writes sphere_demo.png next to this file)
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxlag as jl

jax.config.update("jax_enable_x64", True)


def lagrangian(q, qd, args):
    r, theta = q  # θ measured from the top of the sphere
    rd, thetad = qd
    m, g = args["m"], args["g"]
    return 0.5 * m * (rd**2 + r**2 * thetad**2) - m * g * r * jnp.cos(theta)


def on_sphere(q, args):
    return jnp.array([q[0] - args["R"]])  # r − R ≥ 0 as a unilateral constraint


def camera(q, qd):
    """What a camera sees: the Cartesian position (x, y) of the particle."""
    return q[0] * jnp.array([jnp.sin(q[1]), jnp.cos(q[1])])


def main():
    true = {"m": 1.0, "g": 9.81, "R": 2.0}
    theta0 = 0.05
    q0, qd0 = jnp.array([true["R"], theta0]), jnp.array([0.0, 0.0])
    ts = np.linspace(0.0, 2.6, 261)
    # Post-processing below is NumPy on host copies: eager jax.numpy operations would each
    # compile a small program (see "Compile time" in the README).
    camera_path = jax.jit(jax.vmap(lambda q: camera(q, None)))

    # --- 1. simulate: on the sphere, release at λ = 0, free flight ------------------------------
    sliding = jl.System(lagrangian, holonomic=on_sphere, unilateral=0)
    traj = jl.simulate(sliding, q0, qd0, ts, args=true)
    q, energy = np.asarray(traj.q), np.asarray(traj.energy)
    theta = q[:, 1]
    on = np.asarray(traj.active)[:, 0]
    normal_force = np.asarray(traj.multipliers)[:, 0]
    closed_form = true["m"] * true["g"] * (3 * np.cos(theta) - 2 * np.cos(theta0))
    release = np.asarray(traj.events.q)[0]
    t_release, theta_release = float(np.asarray(traj.events.time)[0]), float(release[1])
    expected = float(np.arccos(2.0 / 3.0 * np.cos(theta0)))
    print(f"events: {traj.events.kinds()[:2]}")
    print(
        f"normal force vs m g (3cos θ − 2cos θ0) while on the sphere: max error "
        f"{np.max(np.abs(np.where(on, normal_force - closed_form, 0.0))):.1e}"
    )
    print(
        f"released at t = {t_release:.6f} s, θ = {np.degrees(theta_release):.8f}° "
        f"(closed form arccos(2/3 cos θ0) = {np.degrees(expected):.8f}°)"
    )
    print(f"energy drift across the release: {np.max(np.abs(energy - energy[0])):.1e}")

    # --- 2. fit g and R from noisy camera data taken while the particle is on the sphere ----------
    window = ts[ts < t_release - 0.05]
    clean = np.asarray(camera_path(q[: window.shape[0]]))
    noise = 0.002
    observed = clean + noise * np.random.default_rng(0).standard_normal(clean.shape)
    on_the_sphere = jl.System(lagrangian, holonomic=on_sphere)  # bilateral while in contact
    guess = {"g": 8.0, "R": 2.4}
    result = jl.fit(
        on_the_sphere,
        guess,
        jl.Experiment(window, observed, q0, qd0),
        observe=camera,
        args={"m": 1.0},
        transforms={"g": jl.Positive(), "R": jl.Positive()},
    )
    print(
        f"fit: Levenberg–Marquardt, {result.num_steps} steps, residual std "
        f"{float(result.residual_std):.4f} (noise {noise})"
    )
    for name in ("g", "R"):
        value, se = float(result.params[name]), float(result.standard_errors[name])
        print(
            f"  {name}: true {true[name]:.4f}   start {guess[name]:.4f}   recovered {value:.4f} "
            f"± {se:.4f}   ({(value - true[name]) / se:+.2f} standard errors)"
        )

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: skipping the plot (pip install 'jaxlag[examples]')")
        return
    fitted_args = {"m": 1.0, **result.params}
    fitted = np.asarray(
        camera_path(
            jl.simulate(
                on_the_sphere,
                *jl.consistent_initial_state(on_the_sphere, q0, qd0, 0.0, fitted_args),
                window,
                args=fitted_args,
            ).q
        )
    )
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    xy = np.asarray(camera_path(q))
    circle = np.linspace(0, 2 * np.pi, 200)
    axes[0].plot(true["R"] * np.sin(circle), true["R"] * np.cos(circle), "k-", lw=0.5)
    axes[0].plot(xy[on, 0], xy[on, 1], "b-", label="on the sphere")
    axes[0].plot(xy[~on, 0], xy[~on, 1], "r-", label="free flight")
    axes[0].plot(
        *(release[0] * np.array([np.sin(release[1]), np.cos(release[1])])), "ko", label="release (event)"
    )
    axes[0].set(aspect="equal", title="path", xlim=(-0.5, 3.5), ylim=(-1.5, 2.5))
    axes[0].legend(fontsize=8)
    axes[1].plot(np.degrees(theta), normal_force, label="λ (jaxlag multiplier)")
    axes[1].plot(np.degrees(theta[on]), closed_form[on], "--", label="m g (3cos θ − 2cos θ0)")
    axes[1].axvline(np.degrees(expected), c="k", lw=0.5)
    axes[1].set(xlabel="θ [deg]", ylabel="normal force [N]", title="constraint force")
    axes[1].legend(fontsize=8)
    axes[2].plot(window, observed[:, 0], ".", ms=2, label="x observed")
    axes[2].plot(window, observed[:, 1], ".", ms=2, label="y observed")
    axes[2].plot(window, fitted[:, 0], "-", label="x fitted")
    axes[2].plot(window, fitted[:, 1], "-", label="y fitted")
    axes[2].set(
        xlabel="t [s]", title=f"fit: g = {float(result.params['g']):.3f}, R = {float(result.params['R']):.4f}"
    )
    axes[2].legend(fontsize=8)
    fig.tight_layout()
    out = Path(__file__).with_name("sphere_demo.png")
    fig.savefig(out, dpi=100)
    print(f"plot written to {out}")


if __name__ == "__main__":
    main()
