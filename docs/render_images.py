"""Regenerate the pictures of the cookbook: run each page's python blocks in order, as one script,
with docs/images/ as working directory, so that each committed PNG is exactly what its page's code
draws. Usage, from the repository root: ``python docs/render_images.py [page-stem ...]``; the stem
``systems`` draws the picture of each ready model of docs/api/systems.md (:func:`render_models`).

The blocks are found as tests/test_readme.py finds them (it runs the same scripts in a temporary
directory); needs matplotlib, and SciPy for the LQR page (``pip install ".[docs]"``).
"""

import os
import pathlib
import re
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
_FENCE = re.compile(r"^(\s*)```(\S*)\s*$")


def page_script(page):
    """The page's ```python blocks, each at its own line numbers (other lines blank)."""
    lines, language, indent = [], None, ""
    for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), start=1):
        fence = _FENCE.match(line)
        if language is None:
            if fence:
                indent, language = fence.group(1), fence.group(2)
        elif fence and not fence.group(2):
            language = None
        elif language == "python":
            lines += [""] * (number - 1 - len(lines))
            lines.append(line[len(indent) :] if line.startswith(indent) else line)
    return "\n".join(lines) + "\n"


def main(stems):
    images = ROOT / "docs" / "images"
    images.mkdir(exist_ok=True)
    # This checkout's jaxlag first, whatever is installed; no windows.
    path = os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path, "MPLBACKEND": "Agg"}
    if not stems or "systems" in stems:
        print("--- docs/api/systems.md", flush=True)
        # In a fresh interpreter, as the pages are: this checkout's jaxlag, the Agg backend.
        code = f"import sys; sys.path.insert(0, {str(ROOT / 'docs')!r}); import render_images as r"
        code += "; r.render_models()"
        subprocess.run([sys.executable, "-c", code], cwd=images, check=True, env=env)
    for page in sorted((ROOT / "docs" / "cookbook").glob("*.md")):
        source = page_script(page)
        if (stems and page.stem not in stems) or not source.strip():
            continue
        with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False, encoding="utf-8") as script:
            script.write(source)
        print(f"--- {page.relative_to(ROOT)}", flush=True)
        try:
            subprocess.run([sys.executable, script.name], cwd=images, check=True, env=env)
        finally:
            os.unlink(script.name)


if __name__ == "__main__":
    main(sys.argv[1:])


# ----------------------------------------------------------------------------- ready models
def render_models():
    """One picture per model of ``jaxlag.systems``, ``systems-<model>.png`` in the working
    directory: the model at a representative state, drawn with ``jaxlag.plot``, and where a path
    tells more, a short simulation of it with the default parameters."""
    import io

    import jax
    import jax.numpy as jnp
    import matplotlib.pyplot as plt
    import numpy as np
    from PIL import Image  # matplotlib's own dependency

    import jaxlag as jl
    from jaxlag import coordinates, plot, rotations, systems

    jax.config.update("jax_enable_x64", True)

    def ring(centre, e1, e2, radius, n=60):  # a circle in the plane spanned by e1, e2 (3-D)
        s = np.linspace(0.0, 2 * np.pi, n)
        return np.asarray(centre) + radius * (np.cos(s)[:, None] * e1 + np.sin(s)[:, None] * e2)

    def figure(three_d=False):
        # Shown about 360 px wide on the page (a card of docs/api/systems.md): 480 px at 120 dpi.
        fig = plt.figure(figsize=(4.0, 3.4))
        ax = fig.add_subplot(projection="3d" if three_d else None)
        if three_d:
            ax.set_box_aspect((1, 1, 1))
            ax.set(xticklabels=[], yticklabels=[], zticklabels=[])
        else:
            ax.set_aspect("equal")
            ax.tick_params(labelsize=8)
        return fig, ax

    def save(fig, name, title):
        fig.axes[0].set_title(title, fontsize=10)
        fig.tight_layout()
        buffer = io.BytesIO()
        fig.savefig(buffer, dpi=120)
        plt.close(fig)
        # Line drawings: a 64-colour palette looks the same at a third of the size.
        picture = Image.open(buffer).convert("RGB").quantize(colors=64, dither=Image.Dither.NONE)
        picture.save(f"systems-{name}.png", optimize=True)

    def run(system, q0, qd0, t1, n=80, args=None):
        return jl.simulate(
            system, jnp.asarray(q0, float), jnp.asarray(qd0, float), jnp.linspace(0, t1, n), args=args
        )

    e = np.eye(3)

    # planar chains: a short swing, a few instants overlaid
    traj = run(systems.simple_pendulum(), [1.2], [0.0], 1.0)
    fig, ax = figure()
    plot.snapshots(lambda q: coordinates.planar_chain(q, 1.0), traj, frames=4, ax=ax, origin=(0, 0))
    save(fig, "simple_pendulum", "θ from the downward vertical")

    traj = run(systems.double_pendulum(), [2.0, 2.6], [0.0, 0.0], 1.5, n=150)
    fig, ax = figure()
    points = jax.vmap(lambda q: coordinates.planar_chain(q, 1.0))(traj.q)
    ax.plot(points[:, 1, 0], points[:, 1, 1], color="grey", lw=0.8)
    plot.snapshots(lambda q: coordinates.planar_chain(q, 1.0), traj, frames=[0, 149], ax=ax, origin=(0, 0))
    save(fig, "double_pendulum", "(θ₁, θ₂); the tip's path")

    traj = run(systems.n_link_pendulum(4), [1.0, 1.2, 1.4, 1.6], jnp.zeros(4), 0.8)
    fig, ax = figure()
    plot.snapshots(lambda q: coordinates.planar_chain(q, 1.0), traj, frames=3, ax=ax, origin=(0, 0))
    save(fig, "n_link_pendulum", "n = 4, three instants")

    traj = run(systems.free_chain(4, 2), [0, 0, 1, 0, 2, 0, 3, 0], [0, -1, 0, 0, 0, 0, 0, 1], 2.0)
    fig, ax = figure()
    plot.snapshots(lambda q: q.reshape(4, 2), traj, frames=4, ax=ax)
    save(fig, "free_chain", "n = 4 in 2-D, tumbling")

    fig, ax = figure()
    x, th, l = 0.3, 0.5, 1.0
    ax.plot([-1.2, 1.6], [-0.12, -0.12], color="k", lw=1)  # the track
    ax.add_patch(plt.Rectangle((x - 0.3, -0.1), 0.6, 0.2, color="tab:grey"))
    plot.chain([[x + l * np.sin(th), l * np.cos(th)]], ax=ax, origin=(x, 0.0))
    ax.annotate("", xy=(x + 0.8, 0), xytext=(x + 0.35, 0), arrowprops={"arrowstyle": "->"})
    save(fig, "cart_pole", "(x, θ), θ from upright; force")

    # particles on curves and surfaces
    traj = run(systems.spherical_pendulum(), [1.0, 0.0], [0.0, 3.0], 2.0, n=150)
    bob = coordinates.spherical(1.0, jnp.pi - traj.q[:, 0], traj.q[:, 1])
    fig, ax = figure(three_d=True)
    ax.plot(*np.asarray(bob).T, color="grey", lw=0.8)
    plot.chain(bob[-1:], ax=ax, origin=(0, 0, 0))
    save(fig, "spherical_pendulum", "(θ, φ); the bob's path")

    fig, ax = figure(three_d=True)
    th, phi = 0.9, 0.6
    ax.plot(*ring([0, 0, 0], np.array([np.cos(phi), np.sin(phi), 0]), e[2], 1.0).T, color="k", lw=1)
    ax.plot([0, 0], [0, 0], [-1.2, 1.2], "k--", lw=0.8)  # the spin axis
    bead = [np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), -np.cos(th)]
    plot.chain([bead], ax=ax, origin=(0, 0, 0), lw=1)
    save(fig, "bead_on_hoop", "θ from the bottom; hoop spins")

    fig, ax = figure()
    r = np.linspace(-1.2, 1.2, 50)
    ax.plot(r, r**2, "k", lw=1)
    ax.plot([0, 0], [-0.1, 1.5], "k--", lw=0.8)
    plot.chain([[0.7, 0.49]], ax=ax, ms=8)
    save(fig, "bead_on_rotating_parabola", "wire z = c r², spinning")

    alpha = 0.5
    system = systems.particle_on_cone()
    traj = run(system, [1.0, 0.0], [0.0, 2.0], 2.0, n=150)
    r, phi = traj.q[:, 0], traj.q[:, 1]
    path = coordinates.cylindrical(r * np.sin(alpha), phi, r * np.cos(alpha))
    fig, ax = figure(three_d=True)
    for phi0 in np.linspace(0, 2 * np.pi, 9)[:-1]:
        ax.plot(
            [0, 1.4 * np.sin(alpha) * np.cos(phi0)],
            [0, 1.4 * np.sin(alpha) * np.sin(phi0)],
            [0, 1.4 * np.cos(alpha)],
            color="0.8",
            lw=0.6,
        )
    ax.plot(*np.asarray(path).T, lw=1.2)
    save(fig, "particle_on_cone", "(r, φ) on the cone; a path")

    traj = run(systems.particle_on_sphere(), [1.0, 0.4, 0.0], [0.0, 0.0, 2.5], 1.5, n=150)
    path = coordinates.spherical(traj.q[:, 0], traj.q[:, 1], traj.q[:, 2])
    fig, ax = figure(three_d=True)
    for phi0 in np.linspace(0, np.pi, 5)[:-1]:
        ax.plot(*ring([0, 0, 0], np.array([np.cos(phi0), np.sin(phi0), 0]), e[2], 1.0).T, color="0.8", lw=0.6)
    ax.plot(*ring([0, 0, 0], e[0], e[1], 1.0).T, color="0.8", lw=0.6)
    ax.plot(*np.asarray(path).T, lw=1.2)
    save(fig, "particle_on_sphere", "(r, θ, φ), θ from the top")

    fig, ax = figure()
    th = np.linspace(0, 4 * np.pi, 300)
    ax.plot(th * np.cos(th), th * np.sin(th), "k", lw=1)
    plot.chain([[3 * np.pi * np.cos(3 * np.pi), 0.0]], ax=ax, ms=8)
    save(fig, "spiral", "r = a θ")

    traj = run(systems.kepler(), [1.0, 0.0], [0.0, 1.25], 22.0, n=300)
    orbit = coordinates.polar(traj.q[:, 0], traj.q[:, 1])
    fig, ax = figure()
    ax.plot(*np.asarray(orbit).T, lw=1.2)
    ax.plot(0, 0, "k*", ms=8)
    save(fig, "kepler", "(r, φ); a bound orbit")

    traj = run(systems.charged_particle(), [0, 0, 0], [1.0, 0.0, 0.15], 18.0, n=300)
    fig, ax = figure(three_d=True)
    ax.plot(*np.asarray(traj.q).T, lw=1.2)
    ax.plot([0, 0], [0, 0], [0, 2.7], "k--", lw=0.8)  # along B
    save(fig, "charged_particle", "(x, y, z); gyration about B")

    # rolling and sliding
    traj = run(systems.rolling_disk(), [0, 0, 0, 0], [1.0, 0.0, 0.5, 1.0], 12.0, n=120)
    fig, ax = figure()
    ax.plot(traj.q[:, 0], traj.q[:, 1], color="grey", lw=0.8)
    for k in (0, 40, 80):
        x, y, phi = np.asarray(traj.q[k, :3])
        plot.chain(
            [[x - np.cos(phi), y - np.sin(phi)], [x + np.cos(phi), y + np.sin(phi)]],
            ax=ax,
            marker=None,
            color="tab:blue",
        )
    save(fig, "rolling_disk", "(x, y, φ, θ): contact path")

    fig, ax = figure()
    alpha, s, R = 0.5, 1.2, 0.4
    down = np.array([np.cos(alpha), -np.sin(alpha)])
    normal = np.array([np.sin(alpha), np.cos(alpha)])
    ax.plot([0, 3 * down[0]], [0, 3 * down[1]], "k", lw=1)
    ax.plot(*ring(np.r_[s * down + R * normal, 0], e[0], e[1], R)[:, :2].T, lw=1.5)
    plot.chain([s * down + R * normal], ax=ax, origin=s * down, marker=None, lw=1)
    save(fig, "disk_on_incline", "s down the slope, s = R θ")

    traj = run(systems.knife_edge(), [0, 0, 0], [0, 0, 1.5], 4.0, n=120)
    fig, ax = figure()
    ax.plot(traj.q[:, 1], traj.q[:, 0], color="grey", lw=0.8)  # y across, x down the slope
    for k in (20, 50, 80, 110):
        x, y, th = np.asarray(traj.q[k])
        plot.chain(
            [[y - 0.15 * np.sin(th), x - 0.15 * np.cos(th)], [y + 0.15 * np.sin(th), x + 0.15 * np.cos(th)]],
            ax=ax,
            marker=None,
            color="tab:blue",
        )
    ax.invert_yaxis()
    ax.set_aspect("auto")
    save(fig, "knife_edge", "skate on a slope (x down)")

    # rigid bodies in 3-D
    system = systems.heavy_top()
    traj = run(system, [0.0, 0.5, 0.0], [0.0, 0.0, 150.0], 1.0, n=200)
    tip = jax.vmap(lambda q: rotations.euler_matrix(q, "zxz")[:, 2])(traj.q)
    fig, ax = figure(three_d=True)
    plot.body_axes(np.zeros(3), rotations.euler_matrix(traj.q[-1], "zxz"), ax=ax, length=0.25)
    ax.plot(*(0.25 * np.asarray(tip)).T, color="grey", lw=0.8)
    save(fig, "heavy_top", "(φ, θ, ψ) zxz; body axes")

    fig, ax = figure(three_d=True)
    R = rotations.euler_matrix(jnp.array([0.1, 0.5, 0.2]), "zxz")
    plot.body_axes(np.zeros(3), R, ax=ax, length=0.6)
    half = np.array([2.0, 3.0, 4.0]) ** -0.5 * 0.5  # a box, longest along the smallest moment
    for i, j in ((0, 1), (1, 2), (2, 0)):
        for s in (-1, 1):
            k = 3 - i - j
            corners = [
                s * half[k] * e[k] + a * half[i] * e[i] + b * half[j] * e[j]
                for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))
            ]
            plot.chain(
                np.asarray(corners) @ np.asarray(R).T, ax=ax, closed=True, marker=None, lw=0.8, color="0.5"
            )
    save(fig, "torque_free_body", "(φ, θ, ψ); I1 < I2 < I3")

    fig, ax = figure(three_d=True)
    a, b = 0.5, 0.6
    Ro = rotations.axis_rotation("z", a)
    Ri = Ro @ rotations.axis_rotation("x", b)
    Ro, Ri = np.asarray(Ro), np.asarray(Ri)
    ax.plot(*ring([0, 0, 0], Ro[:, 0], Ro[:, 2], 0.5).T, color="tab:grey", lw=1.5)  # outer gimbal
    ax.plot(*ring([0, 0, 0], Ri[:, 1], Ri[:, 2], 0.4).T, color="tab:olive", lw=1.5)  # inner gimbal
    ax.plot(*ring(0.1 * Ri[:, 2], Ri[:, 0], Ri[:, 1], 0.25).T, color="tab:blue", lw=2)  # rotor
    plot.chain([0.35 * Ri[:, 2]], ax=ax, origin=-0.35 * Ri[:, 2], marker=None, lw=1, color="k")
    ax.plot([0, 0], [0, 0], [-0.6, 0.6], "k--", lw=0.8)
    save(fig, "gyroscope", "gimbals α, β; rotor γ")

    fig, ax = figure(three_d=True)
    th, phi, R0 = 1.2, 0.4, 0.5
    Rd = np.asarray(rotations.euler_matrix(jnp.array([phi, th, 0.0]), "zxz"))
    centre = np.array([0.0, 0.0, R0 * np.sin(th)])
    ax.plot(*ring(centre, Rd[:, 0], Rd[:, 1], R0).T, lw=1.5)
    plot.body_axes(centre, Rd, ax=ax, length=0.35)
    ax.plot(*ring([0, 0, 0], e[0], e[1], 0.8).T, color="0.8", lw=0.6)
    save(fig, "rolling_disk_3d", "(x, y, z, φ, θ, ψ); leaning")

    fig, ax = figure(three_d=True)
    R0 = 0.1
    ax.plot(*ring([0, 0, 0], e[0], e[1], 1.0).T, color="k", lw=1)  # the table
    centre = np.array([0.4, 0.2, R0])
    ax.plot(*ring([0.4, 0.2, 0], e[0], e[1], np.hypot(0.4, 0.2) * 0.9).T, color="0.7", lw=0.6)
    for k in range(3):
        ax.plot(*ring(centre, e[k], e[(k + 1) % 3], R0).T, color="tab:blue", lw=1)
    plot.body_axes(centre, np.eye(3), ax=ax, length=0.2)
    ax.plot([0, 0], [0, 0], [0, 0.5], "k--", lw=0.8)  # Ω
    ax.set_zlim(0, 0.6)
    ax.set_box_aspect((1, 1, 0.4))
    save(fig, "ball_on_turntable", "(x, y) + quaternion; table spins")

    # the Whipple bicycle, side view at its reference configuration (x forward, z up)
    p = systems.default_args(systems.whipple_bicycle)
    w, c, lam, rR, rF = p["w"], p["c"], p["lam"], p["rR"], p["rF"]
    fig, ax = figure()
    fig.set_size_inches(4.0, 2.6)
    ax.plot([-0.5, w + 0.6], [0, 0], "k", lw=1)
    for x, r in ((0.0, rR), (w, rF)):
        ax.plot(*ring([x, r, 0], e[0], e[1], r)[:, :2].T, lw=1.5, color="tab:grey")
    steer_foot = np.array([w + c, 0.0])
    steer_dir = np.array([-np.sin(lam), np.cos(lam)])
    top = steer_foot + 1.05 * steer_dir
    plot.chain([[0.0, rR], [p["xB"], -p["zB"]], top], ax=ax, marker=None, lw=1.5)  # rear frame
    # front frame: from the front hub to the steer axis, then along the axis to the bars
    hub_on_axis = steer_foot + np.dot(np.array([w, rF]) - steer_foot, steer_dir) * steer_dir
    plot.chain(
        [hub_on_axis, top, [p["xH"], -p["zH"]]],
        ax=ax,
        origin=[w, rF],
        marker=None,
        lw=1.5,
        color="tab:orange",
    )
    ax.plot(p["xB"], -p["zB"], "ko", ms=5)  # rider's centre of mass
    save(fig, "whipple_bicycle", "side view (x forward, z up)")

    # robots read from MJCF (jaxlag.robots, needs MuJoCo): link origins from forward kinematics
    import jaxlag.robots as jlr

    tree = systems.default_args(systems.robot_arm)
    fig, ax = figure(three_d=True)
    for q, color in (([0.0, 0.0, 0.0, 0.0, 0.0, 0.0], "0.7"), ([0.6, 0.5, -0.9, 0.4, 0.8, 0.0], "tab:blue")):
        poses = jlr.forward_kinematics(tree, jnp.asarray(q))
        tip = poses.translation[-1] + poses.rotation[-1] @ jnp.array([0.08, 0.0, 0.0])
        points = np.vstack([np.asarray(poses.translation), np.asarray(tip)[None]])
        plot.chain(points, ax=ax, origin=(0.0, 0.0, 0.0), color=color)
    plot.body_axes(tip, poses.rotation[-1], ax=ax, length=0.1)
    ax.set(xlim=(-0.1, 0.8), ylim=(-0.1, 0.8), zlim=(0.0, 0.8))
    save(fig, "robot_arm", "six hinges from MJCF; two poses")

    tree = systems.default_args(systems.space_robot)
    q = jnp.asarray([0.0, 0.0, 0.0, 0.97, 0.05, 0.1, 0.2, 0.5, -0.6, -0.4, 0.7])
    q = q.at[3:7].set(q[3:7] / jnp.linalg.norm(q[3:7]))
    poses = jlr.forward_kinematics(tree, q)
    R, p = np.asarray(poses.rotation[0]), np.asarray(poses.translation[0])
    fig, ax = figure(three_d=True)
    half = np.array([0.3, 0.2, 0.15])
    for k in range(3):  # the base: a box, its twelve edges
        i, j = (k + 1) % 3, (k + 2) % 3
        for s in (-1, 1):
            corners = [
                s * half[k] * e[k] + a * half[i] * e[i] + b * half[j] * e[j]
                for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))
            ]
            plot.chain(p + np.asarray(corners) @ R.T, ax=ax, closed=True, marker=None, lw=0.8, color="0.5")
    for upper, fore in ((1, 2), (3, 4)):
        tip = poses.translation[fore] + poses.rotation[fore] @ jnp.array([0.4, 0.0, 0.0])
        plot.chain(np.asarray([poses.translation[upper], poses.translation[fore], tip]), ax=ax)
    plot.body_axes(p, R, ax=ax, length=0.25)
    ax.set(xlim=(-0.5, 1.2), ylim=(-0.85, 0.85), zlim=(-0.85, 0.85))
    save(fig, "space_robot", "free base (quaternion), two arms")
