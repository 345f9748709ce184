"""jaxlag.plot draws what it says (the data of the artists are the points, axes and residuals given)
and matplotlib stays optional: ``import jaxlag`` does not import it."""

import os
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")

import equinox as eqx
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import pytest
from PIL import Image

import jaxlag as jl
from jaxlag import coordinates, plot, rotations


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _pendulum_lagrangian(q, qd, args):  # polar (r, θ), θ from the downward vertical
    return 0.5 * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2) + 9.81 * q[0] * jnp.cos(q[1])


@pytest.fixture(scope="module")
def rod_pendulum():
    """A pendulum on a rod r − 1 = 0, as a constrained trajectory (Baumgarte-free, so f drifts a
    little: the residuals are small but not all zero)."""
    system = jl.System(_pendulum_lagrangian, holonomic=lambda q: jnp.array([q[0] - 1.0]))
    return jl.simulate(system, jnp.array([1.0, 1.0]), jnp.array([0.0, 0.5]), jnp.linspace(0.0, 1.0, 11))


def test_import_jaxlag_does_not_import_matplotlib():
    """And without matplotlib, a drawing asks for it by name."""
    code = """
import sys, jaxlag
assert 'matplotlib' not in sys.modules, 'matplotlib was imported'
sys.modules['matplotlib'] = None  # as if it were not installed
try:
    jaxlag.plot.chain([[0.0, 0.0], [1.0, 0.0]])
except ImportError as error:
    assert 'pip install matplotlib' in str(error), error
else:
    raise AssertionError('no ImportError')
"""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=120)


def test_chain_draws_the_points_with_origin_and_closure():
    angles = jnp.array([0.3, -0.4, 1.1])
    points = np.asarray(coordinates.planar_chain(angles, jnp.array([1.0, 0.5, 0.8])))
    line = plot.chain(points, origin=(0.0, 0.0))
    np.testing.assert_array_equal(np.asarray(line.get_xydata()), np.vstack([[0.0, 0.0], points]))
    assert line.axes.get_aspect() == 1.0  # a figure made here keeps lengths true

    fig, ax = plt.subplots()
    loop = plot.chain(points, ax=ax, closed=True, color="k")
    assert loop.axes is ax and loop.get_color() == "k"
    np.testing.assert_array_equal(np.asarray(loop.get_xydata()), np.vstack([points, points[:1]]))

    with pytest.raises(ValueError, match=r"shape \(n_points, 2\) or \(n_points, 3\), got shape \(3,\)"):
        plot.chain(np.zeros(3))
    with pytest.raises(ValueError, match="origin has 3 coordinates but the points have 2"):
        plot.chain(points, origin=(0.0, 0.0, 0.0))


def test_snapshots_draw_the_chain_at_the_chosen_states(rod_pendulum):
    def bob(q):
        return coordinates.polar(q[0], q[1] - jnp.pi / 2)[None]  # θ from the downward vertical

    lines = plot.snapshots(bob, rod_pendulum, frames=3, origin=(0.0, 0.0))
    assert len(lines) == 3
    for line, k in zip(lines, [0, 5, 10]):
        expected = np.vstack([[0.0, 0.0], np.asarray(bob(rod_pendulum.q[k]))])
        np.testing.assert_allclose(np.asarray(line.get_xydata()), expected, rtol=0, atol=1e-15)
    alphas = [line.get_alpha() for line in lines]
    assert alphas == sorted(alphas) and alphas[-1] == 1.0  # later states are drawn stronger

    chosen = plot.snapshots(bob, rod_pendulum.q, frames=[-1, 2])
    np.testing.assert_allclose(chosen[0].get_xydata()[-1], np.asarray(bob(rod_pendulum.q[10]))[0])
    with pytest.raises(ValueError, match="frame index 11 is out of range for 11 saved states"):
        plot.snapshots(bob, rod_pendulum, frames=[11])
    with pytest.raises(ValueError, match=r"coordinates of shape \(times, n\), got shape \(2, 11, 2\)"):
        plot.snapshots(bob, jnp.stack([rod_pendulum.q, rod_pendulum.q]))


def test_body_axes_are_the_scaled_columns_of_R():
    R = np.asarray(rotations.euler_matrix(jnp.array([0.3, 0.7, -1.2]), "zxz"))
    x_c = np.array([0.1, -0.2, 0.5])
    lines = plot.body_axes(x_c, R, length=0.4)
    assert lines[0].axes.name == "3d"
    for k, line in enumerate(lines):
        xs, ys, zs = line.get_data_3d()
        np.testing.assert_allclose(np.stack([xs, ys, zs], axis=1), np.stack([x_c, x_c + 0.4 * R[:, k]]))
    assert [line.get_color() for line in lines] == list(plot.AXIS_COLORS)

    fig, ax = plt.subplots()
    with pytest.raises(ValueError, match="projection='3d'"):
        plot.body_axes(x_c, R, ax=ax)
    with pytest.raises(
        ValueError, match=r"x_c of shape \(3,\) and R of shape \(3, 3\), got \(3,\) and \(9,\)"
    ):
        plot.body_axes(x_c, R.reshape(-1))


def test_energy_and_constraint_drift_plot_the_trajectory_values(rod_pendulum):
    e = np.asarray(rod_pendulum.energy)
    line = plot.energy(rod_pendulum)
    np.testing.assert_array_equal(line.get_ydata(), np.abs((e - e[0]) / abs(e[0])))
    np.testing.assert_array_equal(line.get_xdata(), np.asarray(rod_pendulum.t))
    assert line.axes.get_yscale() == "log"
    signed = plot.energy(rod_pendulum, values=e - e[0], scale=2.0, log=False)
    np.testing.assert_array_equal(signed.get_ydata(), (e - e[0]) / 2.0)
    with pytest.raises(ValueError, match=r"E\(0\) = 0.*pass scale="):
        plot.energy(rod_pendulum, values=e - e[0])
    with pytest.raises(ValueError, match=r"values has shape \(3,\), but the trajectory has 11 save times"):
        plot.energy(rod_pendulum, values=np.ones(3))

    f, f_dot, _ = (np.asarray(r) for r in rod_pendulum.constraint_residuals)
    lines = plot.constraint_drift(rod_pendulum)
    assert [line.get_label() for line in lines] == ["$|f|$", r"$|\dot f|$"]  # no velocity constraints: no |g|
    np.testing.assert_array_equal(lines[0].get_ydata(), np.abs(f).max(axis=1))
    np.testing.assert_array_equal(lines[1].get_ydata(), np.abs(f_dot).max(axis=1))
    assert np.max(lines[0].get_ydata()) < 1e-8  # the picture of a healthy run

    free = jl.simulate(jl.System(_pendulum_lagrangian), jnp.ones(2), jnp.zeros(2), jnp.linspace(0, 0.1, 3))
    with pytest.raises(ValueError, match="no constraints"):
        plot.constraint_drift(free)


def test_constraint_drift_counts_only_active_unilateral_rows():
    def lagrangian(q, qd, args):  # a particle on top of a sphere of radius 1, polar (r, θ) from the top
        return 0.5 * (qd[0] ** 2 + q[0] ** 2 * qd[1] ** 2) - 9.81 * q[0] * jnp.cos(q[1])

    sphere = jl.System(lagrangian, holonomic=lambda q: jnp.array([q[0] - 1.0]), unilateral=0)
    traj = jl.simulate(sphere, jnp.array([1.0, 0.3]), jnp.zeros(2), jnp.linspace(0.0, 1.0, 9))
    active = np.asarray(traj.active[:, 0])
    assert active[0] and not active[-1]  # it leaves the sphere
    (line, _) = plot.constraint_drift(traj)
    f = np.abs(np.asarray(traj.constraint_residuals[0][:, 0]))
    np.testing.assert_array_equal(line.get_ydata(), np.where(active, f, 0.0))


def test_animate_chain_writes_a_gif_with_one_frame_per_state(rod_pendulum, tmp_path):
    def bob(q):
        return coordinates.polar(q[0], q[1] - jnp.pi / 2)[None]

    path = tmp_path / "pendulum.gif"
    plot.animate_chain(bob, rod_pendulum, path, every=2, origin=(0.0, 0.0), fps=10, dpi=30)
    assert path.stat().st_size > 0
    with Image.open(path) as gif:
        assert gif.n_frames == 6  # save times 0, 2, …, 10
    assert plt.get_fignums() == []  # the figure made for it is closed

    fig, ax = plt.subplots(figsize=(2, 2))
    (dot,) = ax.plot([], [], "o")
    ax.set(xlim=(0, 4), ylim=(0, 4))
    plot.animate(fig, lambda k: dot.set_data([k], [k]), 4, tmp_path / "dot.gif", fps=5, dpi=30)
    with Image.open(tmp_path / "dot.gif") as gif:
        assert gif.n_frames == 4
    with pytest.raises(ValueError, match="every=0 must be at least 1"):
        plot.animate_chain(bob, rod_pendulum, path, every=0)


def test_unreached_saves_are_left_out_and_other_non_finite_values_refused(rod_pendulum):
    """After a terminal event diffrax saves inf times and states: not drawn. A NaN state at a
    reached time is a failed run: an error that names the save, not a silently empty picture."""
    inf = jnp.full(3, jnp.inf)
    ended = eqx.tree_at(
        lambda tr: (tr.t, tr.q, tr.qd),
        rod_pendulum,
        (
            rod_pendulum.t.at[-3:].set(inf),
            rod_pendulum.q.at[-3:].set(jnp.inf),
            rod_pendulum.qd.at[-3:].set(jnp.inf),
        ),
    )
    assert len(plot.energy(ended).get_xdata()) == 8
    assert [len(line.get_xdata()) for line in plot.constraint_drift(ended)] == [8, 8]
    assert len(plot.snapshots(lambda q: q[None], ended, frames=20)) == 8

    failed = eqx.tree_at(lambda tr: tr.q, rod_pendulum, rod_pendulum.q.at[4, 1].set(jnp.nan))
    with pytest.raises(ValueError, match=r"q is not finite at save index 4 .*raise_if_failed"):
        plot.snapshots(lambda q: q[None], failed)
    with pytest.raises(ValueError, match="energy: the energy is not finite at save index 4"):
        plot.energy(failed)
    with pytest.raises(ValueError, match=r"chain: point 1 is not finite: \[nan, 0.0\]"):
        plot.chain([[0.0, 0.0], [np.nan, 0.0]])
