r"""The Whipple bicycle (``jaxlag.systems.whipple_bicycle``), a nonlinear model built from
``RigidBody3D`` bodies, a holonomic front contact and two rolling constraints, linearized with
``jaxlag.analysis.linearize`` and compared with the benchmark of Meijaard, Papadopoulos, Ruina &
Schwab (2007). One compiled, vmapped linearization serves every speed (compiling it is most of
this file's run time: 30–70 s on a shared 2-core CPU).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag.systems as systems

jax.config.update("jax_enable_x64", True)


# ----------------------------------------------------------------------------- Whipple bicycle
# Meijaard, Papadopoulos, Ruina & Schwab (2007), Proc. R. Soc. A 463, 1955: the published
# coefficient matrices of M q̈ + v C1 q̇ + (g K0 + v² K2) q = 0, q = (φ, δ) (their eqs. and
# appendix values for the benchmark bicycle) -- an independent reference for the nonlinear model.
BENCH_M = np.array([[80.81722, 2.31941332208709], [2.31941332208709, 0.29784188199686]])
BENCH_C1 = np.array([[0.0, 33.86641391492494], [-0.85035641456978, 1.68540397397560]])
BENCH_K0 = np.array([[-80.95, -2.59951685249872], [-2.59951685249872, -0.80329488458618]])
BENCH_K2 = np.array([[0.0, 76.59734589573222], [0.0, 2.65431523794604]])


def _benchmark_eigenvalues(v, g=9.81):
    inverse = np.linalg.inv(BENCH_M)
    a = np.block(
        [
            [np.zeros((2, 2)), np.eye(2)],
            [-inverse @ (g * BENCH_K0 + v * v * BENCH_K2), -inverse @ (v * BENCH_C1)],
        ]
    )
    values = np.linalg.eigvals(a)
    return values[np.argsort(values.real)]


@pytest.fixture(scope="module")
def bicycle_spectrum():
    system = systems.whipple_bicycle()

    def at_speed(v):
        # q̈ and λ at the upright state compiled with the linearization (shared subgraph)
        q, qd = systems.bicycle_upright_state(v)
        return (
            *systems.bicycle_eigenvalues(v, return_residual=True),
            system.accelerations(q, qd),
            system.multipliers(q, qd),
        )

    return jax.jit(jax.vmap(at_speed))


def _refine(spectrum, low, high, indicator, iterations=16):
    """A sign change of ``indicator(eigenvalues)`` in [low, high], bracketed on 6-point grids
    (the compiled vmapped spectrum is reused: one shape)."""
    for _ in range(iterations):
        speeds = np.linspace(low, high, 6)
        values = np.asarray(spectrum(jnp.asarray(speeds))[0])
        signs = np.sign([indicator(v) for v in values])
        k = int(np.flatnonzero(np.diff(signs) != 0)[0])
        low, high = speeds[k], speeds[k + 1]
    return 0.5 * (low + high)


def test_whipple_bicycle_matches_benchmark(bicycle_spectrum):
    speeds = np.array([1.0, 3.0, 4.9, 5.0, 6.0, 8.0])
    values, residual, accelerations, normal = bicycle_spectrum(jnp.asarray(speeds))
    assert np.max(np.asarray(residual)) < 1e-9  # lean–steer motion is a quotient
    # upright straight-ahead rolling is a steady motion (q̈ = 0), so linearizing about it is
    # meaningful; the front normal force carries part of the weight
    assert np.max(np.abs(accelerations)) < 1e-12
    total = sum(systems.whipple_bicycle.defaults[k] for k in ("mR", "mB", "mH", "mF")) * 9.81
    assert np.all((0 < normal[:, 0]) & (normal[:, 0] < total))
    for v, ours in zip(speeds, np.asarray(values)):
        reference = _benchmark_eigenvalues(v)
        assert np.allclose(np.sort_complex(ours), np.sort_complex(reference), rtol=1e-9, atol=1e-9)
    # the paper's table at v = 5 m/s (weave, capsize, castering)
    at5 = np.sort_complex(np.asarray(values)[3])
    assert np.allclose(
        at5,
        np.sort_complex(
            np.array(
                [
                    -14.07838969279822,
                    -0.77534188219585 - 4.46486771378823j,
                    -0.77534188219585 + 4.46486771378823j,
                    -0.32286642900409,
                ]
            )
        ),
        atol=1e-9,
    )
    # weave speed (the complex pair crosses the imaginary axis) and capsize speed (the real
    # capsize eigenvalue crosses zero): published v_w = 4.29238253634111, v_c = 6.02426201538837
    weave = _refine(
        bicycle_spectrum, 4.0, 5.0, lambda e: np.max(np.where(np.abs(e.imag) > 1e-9, e.real, -np.inf))
    )
    capsize = _refine(
        bicycle_spectrum, 5.5, 6.5, lambda e: np.max(np.where(np.abs(e.imag) <= 1e-9, e.real, -np.inf))
    )
    assert abs(weave - 4.29238253634111) < 1e-8
    assert abs(capsize - 6.02426201538837) < 1e-8


def test_whipple_bicycle_upright_state_is_on_the_constraints():
    system = systems.whipple_bicycle()
    q, qd = systems.bicycle_upright_state(4.0)
    f, f_dot, g = system.constraint_residuals(q, qd)
    assert np.max(np.abs(np.concatenate([f, f_dot, g]))) < 1e-15
    with pytest.raises(KeyError, match="unknown parameter"):
        systems.bicycle_upright_state(4.0, {"wheelbase": 1.0})
