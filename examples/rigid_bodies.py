"""Rigid bodies in space: a nutating heavy top and the stability of the Whipple bicycle.

1. The heavy symmetric top (``jaxlag.systems.heavy_top``, a ``RigidBody3D`` in Euler angles)
   released without precession nutates between two tilts; p_φ, p_ψ and the energy stay constant.
2. The Whipple bicycle (``jaxlag.systems.whipple_bicycle``: four rigid bodies, a front contact
   constraint and two rolling constraints) linearized with ``jaxlag.analysis.linearize`` about
   upright motion at each speed (one compiled, vmapped function): its lean–steer eigenvalues
   against speed, with the weave and capsize speeds (benchmark of Meijaard et al. 2007:
   4.2924 and 6.0243 m/s).

Run:  python examples/rigid_bodies.py     (writes rigid_bodies.png next to this file)
"""

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxlag as jl
from jaxlag import systems

jax.config.update("jax_enable_x64", True)


def top_nutation():
    top = systems.heavy_top("euler")
    args = dict(systems.heavy_top.defaults)
    q0, qd0 = jnp.array([0.0, 0.5, 0.0]), jnp.array([0.0, 0.0, 150.0])  # spinning, released
    ts = jnp.linspace(0.0, 1.0, 401)
    traj = jl.simulate(top, q0, qd0, ts, args=args)
    drift = {
        name: float(np.ptp(series) / np.max(np.abs(series)))
        for name, series in (
            ("p_phi", traj.momenta[:, 0]),
            ("p_psi", traj.momenta[:, 2]),
            ("energy", traj.energy),
        )
    }
    print(
        "heavy top: tilt θ between "
        f"{float(traj.q[:, 1].min()):.4f} and {float(traj.q[:, 1].max()):.4f} rad; relative drift "
        + ", ".join(f"{k} {v:.1e}" for k, v in drift.items())
    )
    # fast-top estimate of the mean precession rate: m g l / (I3 ω3)
    estimate = args["m"] * args["g"] * args["l"] / (args["I3"] * 150.0)
    print(
        f"  mean precession rate {float(traj.q[-1, 0] / ts[-1]):.4f} rad/s "
        f"(fast-top estimate m g l/(I3 ω3) = {estimate:.4f})"
    )
    return ts, traj


def bicycle_spectrum():
    speeds = jnp.linspace(0.0, 10.0, 101)
    spectrum = jax.jit(jax.vmap(systems.bicycle_eigenvalues))
    start = time.perf_counter()
    values = np.asarray(spectrum(speeds))
    print(
        f"bicycle: {len(speeds)} linearizations in {time.perf_counter() - start:.1f} s "
        "(including compilation)"
    )
    weave = np.array([np.max(np.where(np.abs(v.imag) > 1e-9, v.real, -np.inf)) for v in values])
    capsize = np.array([np.max(np.where(np.abs(v.imag) <= 1e-9, v.real, -np.inf)) for v in values])
    speeds = np.asarray(speeds)

    def crossing(series, low, high):
        inside = np.flatnonzero((speeds >= low) & (speeds <= high))
        k = inside[np.flatnonzero(np.diff(np.sign(series[inside])) != 0)[0]]
        return speeds[k] - series[k] * (speeds[k + 1] - speeds[k]) / (series[k + 1] - series[k])

    print(
        f"  weave speed ≈ {crossing(weave, 3.0, 6.0):.3f} m/s, capsize speed ≈ "
        f"{crossing(capsize, 5.0, 8.0):.3f} m/s (published 4.292, 6.024; linear "
        "interpolation on a 0.1 m/s grid)"
    )
    at5 = values[np.argmin(np.abs(speeds - 5.0))]
    print(
        "  eigenvalues at 5 m/s: "
        + ", ".join(f"{complex(v):.4f}" for v in at5)
        + "  (published −14.0784, −0.7753 ± 4.4649i, −0.3229)"
    )
    return speeds, values


def plot(ts, traj, speeds, values, path):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: skipping the plot (pip install 'jaxlag[examples]')")
        return
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    ax1.plot(np.asarray(ts), np.asarray(traj.q[:, 1]), lw=1)
    ax1.set(xlabel="t [s]", ylabel="tilt θ [rad]", title="heavy top: nutation")
    for k in range(values.shape[1]):
        ax2.plot(speeds, values[:, k].real, "k.", ms=2)
        ax2.plot(speeds, np.abs(values[:, k].imag), "b.", ms=1)
    ax2.set(
        xlabel="speed v [m/s]",
        ylabel="eigenvalue",
        ylim=(-10, 10),
        title="Whipple bicycle: Re s (black), |Im s| (blue)",
    )
    ax2.axhline(0.0, color="gray", lw=0.5)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    print(f"plot written to {path}")


def main():
    ts, traj = top_nutation()
    speeds, values = bicycle_spectrum()
    plot(ts, traj, speeds, values, Path(__file__).with_name("rigid_bodies.png"))


if __name__ == "__main__":
    main()
