"""Pictures of mechanisms and of a simulation's health, with matplotlib (an optional dependency).

Small functions that each draw one thing on a matplotlib axes and return what they drew, so that
they compose with ordinary matplotlib code:

- `chain`: a planar (or spatial) chain or linkage at one instant, from its points;
- `snapshots`: the same chain at several saved times of a trajectory, overlaid;
- `body_axes`: the three body axes of a rigid body in 3-D, from its pose ``(x_c, R)``;
- `energy`: the relative energy drift ``(E(t) − E(0)) / |E(0)|`` over time;
- `constraint_drift`: the constraint residuals ``‖f‖∞``, ``‖ḟ‖∞``, ``‖g‖∞`` over time;
- `animate` and `animate_chain`: an animation saved to a file (a GIF needs only
  Pillow, which comes with matplotlib).

Each takes ``ax=None``: a new figure is made when no axes is given. matplotlib is imported when
one of these functions is called, never by ``import jaxlag``; install it with
``pip install matplotlib`` (or ``pip install "jaxlag[plot]"``).
"""

import pathlib
import warnings
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._custom_types import Validated
from ._trajectory import Trajectory

# matplotlib is optional and imported only when something is drawn, so its classes exist for the
# type checker only; at run time the annotations that name them are `Any` (not checked).
if TYPE_CHECKING:
    from matplotlib.animation import FuncAnimation
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
else:
    FuncAnimation = Axes = Figure = Line2D = Any

__all__ = ["animate", "animate_chain", "body_axes", "chain", "constraint_drift", "energy", "snapshots"]

#: The colours of the body axes x, y, z (red, green, blue, as in most 3-D tools).
AXIS_COLORS = ("tab:red", "tab:green", "tab:blue")


def _pyplot():
    try:
        import matplotlib.pyplot as plt
    except ImportError as error:  # pragma: no cover - exercised only without matplotlib
        raise ImportError(
            "jaxlag.plot draws with matplotlib, an optional dependency that is not installed: "
            'install it with `pip install matplotlib` (or `pip install "jaxlag[plot]"`).'
        ) from error
    return plt


def _new_axes(ax, three_d: bool = False):
    """``(ax, created)``: the given axes, or the axes of a new figure."""
    if ax is not None:
        if three_d and getattr(ax, "name", None) != "3d":
            raise ValueError(
                "this picture is 3-D but the axes given is 2-D: make it with "
                "`fig.add_subplot(projection='3d')` (or pass ax=None for a new figure)."
            )
        return ax, False
    plt = _pyplot()
    fig = plt.figure(figsize=(5.0, 4.5) if three_d else (5.0, 4.0))
    return fig.add_subplot(projection="3d" if three_d else None), True


def _points(points, name: str) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] not in (2, 3):
        raise ValueError(
            f"{name}: expected points of shape (n_points, 2) or (n_points, 3), got shape {p.shape}."
        )
    if not np.all(np.isfinite(p)):
        bad = int(np.argwhere(~np.isfinite(p))[0, 0])
        raise ValueError(f"{name}: point {bad} is not finite: {p[bad].tolist()}.")
    return p


def _with_ends(p: np.ndarray, origin, closed: bool) -> np.ndarray:
    if origin is not None:
        o = np.asarray(origin, dtype=float).reshape(1, -1)
        if o.shape[1] != p.shape[1]:
            raise ValueError(f"origin has {o.shape[1]} coordinates but the points have {p.shape[1]}.")
        p = np.concatenate([o, p])
    if closed:
        p = np.concatenate([p, p[:1]])
    return p


def _states(traj, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """``(q, t)`` from a Trajectory (t its save times) or from an array of rows (t None)."""
    if isinstance(traj, Trajectory):
        q, t = np.asarray(traj.q), np.asarray(traj.t)
    else:
        q, t = np.asarray(traj, dtype=float), None
    if q.ndim != 2:
        raise ValueError(
            f"{name}: expected one trajectory, coordinates of shape (times, n), got shape {q.shape}; "
            "for a batch, pick one member first (e.g. `traj.q[0]`)."
        )
    if t is not None:
        reached = _reached(t, name)
        q, t = q[reached], t[reached]
    _check_finite(q, "q", name)
    return q, t


def _reached(t: np.ndarray, name: str) -> np.ndarray:
    """The saves a run reached: after a terminal event diffrax saves ``inf`` times (and states)."""
    if t.ndim != 1:
        raise ValueError(
            f"{name}: expected one trajectory, save times of shape (times,), got {t.shape}; for a "
            "batch, pick one member first (e.g. `jax.tree.map(lambda x: x[0], traj)`)."
        )
    reached = np.isfinite(t)
    if not reached.any():
        raise ValueError(f"{name}: the trajectory has no finite save time: nothing to draw.")
    return reached


def _check_finite(values: np.ndarray, what: str, name: str) -> None:
    if not np.all(np.isfinite(values)):
        k = int(np.argwhere(~np.isfinite(values))[0, 0])
        raise ValueError(
            f"{name}: {what} is not finite at save index {k} ({values[k].tolist()}): did the run fail? "
            "(`traj.raise_if_failed()` says why; pick the saves before it to draw them.)"
        )


def _frame_indices(frames, count: int, name: str) -> np.ndarray:
    if isinstance(frames, (int, np.integer)):
        if frames < 1:
            raise ValueError(f"{name}: frames={frames} must be at least 1.")
        return np.unique(np.round(np.linspace(0, count - 1, min(int(frames), count))).astype(int))
    index = np.asarray(frames, dtype=int).reshape(-1)
    bad = index[(index < -count) | (index >= count)]
    if bad.size:
        raise ValueError(f"{name}: frame index {int(bad[0])} is out of range for {count} saved states.")
    return index % count


def _positions_at(positions: Callable, q: np.ndarray, name: str) -> np.ndarray:
    points = np.stack([np.asarray(positions(row), dtype=float) for row in q])
    if points.ndim != 3 or points.shape[2] not in (2, 3):
        raise ValueError(
            f"{name}: positions(q) must return points of shape (n_points, 2) or (n_points, 3), "
            f"got shape {points.shape[1:]}."
        )
    _check_finite(points, "positions(q)", name)
    return points


def _one_series(values, t: np.ndarray, what: str) -> np.ndarray:
    v = np.asarray(values, dtype=float)
    if v.shape != t.shape:
        raise ValueError(f"{what} has shape {v.shape}, but the trajectory has {t.shape[0]} save times.")
    return v


def _log_scale(ax) -> None:
    # Residuals that are exactly zero at every save time (e.g. ḟ of a constraint that is linear in
    # q) are left out on a log axis; matplotlib's warning about it says nothing more.
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Data has no positive values")
        ax.set_yscale("log")


# ----------------------------------------------------------------------------- mechanisms
def chain(
    points: Validated[Float[ArrayLike, "points dim"]],
    *,
    ax: Axes | None = None,
    origin: Validated[Float[ArrayLike, " dim"]] | None = None,
    closed: bool = False,
    **line_kwargs: Any,
) -> Line2D:
    """Draw a chain or linkage at one instant: its points joined by straight links.

    ``points`` (n_points, 2) or (n_points, 3) are the joint or bob positions in order, e.g.
    [`jaxlag.coordinates.planar_chain`][jaxlag.coordinates.planar_chain] of the angles; ``origin`` is
    prepended (a fixed pivot)
    and ``closed=True`` joins the last point back to the first (a closed loop). Extra keyword
    arguments go to ``ax.plot`` (the defaults are circles at the joints joined by thick lines).
    A 2-D axes made here has an equal aspect ratio; 3-D points need a 3-D axes.

    Returns the ``Line2D`` (a ``Line3D`` for 3-D points) whose data are the points drawn.
    """
    p = _with_ends(_points(points, "chain"), origin, closed)
    ax, created = _new_axes(ax, three_d=p.shape[1] == 3)
    style = {"marker": "o", "lw": 2.5, "ms": 6, **line_kwargs}
    (line,) = ax.plot(*p.T, **style)
    if created and p.shape[1] == 2:
        ax.set_aspect("equal")
    return line


def snapshots(
    positions: Callable[[Float[Array, " n"]], Float[ArrayLike, "points dim"]],
    traj: Validated[Trajectory | Float[ArrayLike, "times n"]],
    *,
    frames: int | Sequence[int] = 5,
    ax: Axes | None = None,
    origin: Validated[Float[ArrayLike, " dim"]] | None = None,
    closed: bool = False,
    fade: tuple[float, float] = (0.2, 1.0),
    **line_kwargs: Any,
) -> list[Line2D]:
    """Overlay a mechanism at several saved states of a trajectory (a stroboscopic picture).

    ``positions(q)`` maps one row of coordinates to the mechanism's points, as for `chain`;
    ``traj`` is a [`jaxlag.Trajectory`][jaxlag.Trajectory] or its coordinates ``q`` (times, n). ``frames`` is
    the number of evenly spaced saved states to draw (first and last included) or their indices.
    Earlier states are drawn fainter: the opacity rises linearly from ``fade[0]`` to ``fade[1]``.

    Returns the lines drawn, in time order.
    """
    q, _ = _states(traj, "snapshots")
    index = _frame_indices(frames, q.shape[0], "snapshots")
    points = _positions_at(positions, q[index], "snapshots")
    ax, created = _new_axes(ax, three_d=points.shape[2] == 3)
    alphas = np.linspace(fade[0], fade[1], len(index)) if len(index) > 1 else [fade[1]]
    color = line_kwargs.pop("color", line_kwargs.pop("c", "tab:blue"))
    lines = [
        chain(p, ax=ax, origin=origin, closed=closed, color=color, alpha=float(a), **line_kwargs)
        for p, a in zip(points, alphas)
    ]
    if created and points.shape[2] == 2:
        ax.set_aspect("equal")
    return lines


def body_axes(
    x_c: Validated[Float[ArrayLike, "3"]],
    R: Validated[Float[ArrayLike, "3 3"]],
    *,
    ax: Axes | None = None,
    length: float = 1.0,
    colors: Sequence[Any] = AXIS_COLORS,
    **line_kwargs: Any,
) -> list[Line2D]:
    """Draw the three body axes of a rigid body in 3-D, at its pose ``(x_c, R)``.

    ``R`` maps body to world components (as `jaxlag.rotations` builds it and as a
    [`jaxlag.coordinates.RigidBody3D`][jaxlag.coordinates.RigidBody3D] pose returns it), so the body's k-th
    axis in world
    axes is the column ``R[:, k]``: the k-th segment runs from ``x_c`` to ``x_c + length·R[:, k]``,
    in ``colors[k]`` (red, green, blue for x, y, z). Needs a 3-D axes
    (``fig.add_subplot(projection="3d")``); one is made when ``ax`` is None.

    Returns the three ``Line3D``, for the body's x, y and z axes.
    """
    x = np.asarray(x_c, dtype=float)
    rotation = np.asarray(R, dtype=float)
    if x.shape != (3,) or rotation.shape != (3, 3):
        raise ValueError(
            "body_axes: expected x_c of shape (3,) and R of shape (3, 3), "
            f"got {x.shape} and {rotation.shape}."
        )
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(rotation))):
        raise ValueError(f"body_axes: the pose is not finite: x_c = {x}, R = {rotation.tolist()}.")
    ax, _ = _new_axes(ax, three_d=True)
    style = {"lw": 2.5, **line_kwargs}
    lines = []
    for k in range(3):
        end = x + length * rotation[:, k]
        (line,) = ax.plot(*np.stack([x, end]).T, color=colors[k], **style)
        lines.append(line)
    return lines


# ----------------------------------------------------------------------------- health
def energy(
    traj: Trajectory,
    *,
    ax: Axes | None = None,
    values: Validated[Float[ArrayLike, " times"]] | None = None,
    scale: float | None = None,
    log: bool = True,
    **line_kwargs: Any,
) -> Line2D:
    """Plot the relative drift of the energy over time, ``(E(t) − E(0)) / |E(0)|``.

    ``E`` is ``traj.energy`` (the energy function ``h = q̇·∂L/∂q̇ − L``, conserved when ``L`` does
    not depend on time and no forces, drives or dissipation act), or ``values`` (times,): any other
    quantity along the save times, e.g. a momentum. ``scale`` replaces ``|E(0)|`` in the
    denominator (needed when ``E(0) = 0``: pass a typical energy, e.g. ``m g l``). With
    ``log=True`` the absolute value is drawn on a logarithmic axis (the exact zero at ``t = 0`` is
    left out by matplotlib); with ``log=False`` the signed drift on a linear axis. Saves that a
    run did not reach (``inf`` times after a terminal event) are left out; any other non-finite
    value is an error.

    Returns the ``Line2D``; its y-data are the drift values (their absolute values if ``log``).
    """
    t = np.asarray(traj.t)
    reached = _reached(t, "energy")
    e = _one_series(traj.energy if values is None else values, t, "energy: values")
    t, e = t[reached], e[reached]
    _check_finite(e, "the energy" if values is None else "values", "energy")
    if scale is None:
        scale = abs(float(e[0]))
        if scale == 0.0:
            raise ValueError(
                "energy: E(0) = 0, so the relative drift (E − E(0))/|E(0)| is undefined; pass "
                "scale=<a typical energy of the motion> (e.g. m g l) to divide by it instead."
            )
    elif not scale > 0.0:
        raise ValueError(f"energy: scale={scale} must be positive.")
    drift = (e - e[0]) / scale
    ax, _ = _new_axes(ax)
    (line,) = ax.plot(t, np.abs(drift) if log else drift, **{"label": "energy", **line_kwargs})
    if log:
        _log_scale(ax)
    ax.set_xlabel("t")
    ax.set_ylabel("|E − E(0)| / |E(0)|" if log else "(E − E(0)) / |E(0)|")
    return line


def constraint_drift(
    traj: Trajectory,
    *,
    ax: Axes | None = None,
    log: bool = True,
    **line_kwargs: Any,
) -> list[Line2D]:
    """Plot how far the saved states are from the constraint manifold, over time.

    From ``f, ḟ, g = traj.constraint_residuals`` (holonomic ``f(q, t) = 0``, its time derivative,
    and the velocity constraints ``g = A(q, t) q̇ + b = 0``), one line each for
    ``‖f(t)‖∞ = max_k |f_k(t)|``, ``‖ḟ(t)‖∞`` and ``‖g(t)‖∞`` (a kind of constraint the system
    does not have is left out). With unilateral constraints, only the active rows count
    (``traj.active``): a lifted-off contact is not a drift. With ``log=True`` the y axis is
    logarithmic (exact zeros are left out by matplotlib). Saves that a run did not reach
    (``inf`` times after a terminal event) are left out; any other non-finite value is an error.

    Returns the lines drawn, labelled ``|f|``, ``|ḟ|``, ``|g|`` (in matplotlib's mathtext).
    """
    t = np.asarray(traj.t)
    reached = _reached(t, "constraint_drift")
    f, f_dot, g = (np.abs(np.asarray(r, dtype=float))[reached] for r in traj.constraint_residuals)
    t = t[reached]
    if traj.active is not None:
        active = np.asarray(traj.active, dtype=bool)[reached]
        f, f_dot = np.where(active, f, 0.0), np.where(active, f_dot, 0.0)
    for r, what in ((f, "f"), (f_dot, "ḟ"), (g, "g")):
        _check_finite(r, f"the residual {what}", "constraint_drift")
    series = [(f, r"$|f|$"), (f_dot, r"$|\dot f|$"), (g, r"$|g|$")]
    series = [(r.max(axis=1), label) for r, label in series if r.shape[1] > 0]
    if not series:
        raise ValueError("constraint_drift: the system has no constraints, so there is no drift to plot.")
    ax, _ = _new_axes(ax)
    lines = [ax.plot(t, r, **{"label": label, **line_kwargs})[0] for r, label in series]
    if log:
        _log_scale(ax)
    ax.set_xlabel("t")
    ax.set_ylabel("constraint residual (max over rows)")
    ax.legend()
    return lines


# ----------------------------------------------------------------------------- animation
def animate(
    fig: Figure,
    update: Callable[[Any], Any],
    frames: int | Sequence[Any],
    path: str | pathlib.Path,
    *,
    fps: int = 20,
    dpi: float | None = None,
) -> FuncAnimation:
    """Save an animation of ``fig`` to ``path``: ``update(frame)`` redraws the figure for each
    entry of ``frames`` (an int ``N`` means ``0, …, N−1``), as in matplotlib's ``FuncAnimation``.

    A ``.gif`` is written with Pillow (it comes with matplotlib); other suffixes go to
    matplotlib's default writer for them (``.mp4`` needs ffmpeg). Returns the animation.
    """
    _pyplot()
    from matplotlib import animation

    path = pathlib.Path(path)
    anim = animation.FuncAnimation(fig, update, frames=frames, blit=False, cache_frame_data=False)
    if path.suffix.lower() == ".gif":
        anim.save(str(path), writer=animation.PillowWriter(fps=fps), dpi=dpi)
    else:
        anim.save(str(path), fps=fps, dpi=dpi)
    return anim


def animate_chain(
    positions: Callable[[Float[Array, " n"]], Float[ArrayLike, "points 2"]],
    traj: Validated[Trajectory | Float[ArrayLike, "times n"]],
    path: str | pathlib.Path,
    *,
    every: int = 1,
    origin: Validated[Float[ArrayLike, "2"]] | None = None,
    closed: bool = False,
    trace: int | None = -1,
    fps: int = 20,
    dpi: float = 60.0,
    ax: Axes | None = None,
    **line_kwargs: Any,
) -> FuncAnimation:
    """Save an animation of a planar chain or linkage moving along a trajectory.

    One frame per ``every``-th saved state of ``traj`` (a [`jaxlag.Trajectory`][jaxlag.Trajectory] or its
    coordinates ``q`` (times, n)), the mechanism drawn by `chain` from ``positions(q)``
    (points (n_points, 2)) with ``origin`` and ``closed`` as there. ``trace`` is the index of the
    point (in ``positions(q)``) whose path is drawn as it goes, by default the last one (the tip of
    a chain; None: no path). The title shows the time ``t`` of a Trajectory.
    The axis limits are fixed to hold every frame. See `animate` for ``path``, ``fps`` and
    ``dpi``. Returns the animation; the figure is closed when ``ax`` is None.
    """
    q, t = _states(traj, "animate_chain")
    if every < 1:
        raise ValueError(f"animate_chain: every={every} must be at least 1.")
    points = _positions_at(positions, q[::every], "animate_chain")
    if points.shape[2] != 2:
        raise ValueError(f"animate_chain: positions(q) must return 2-D points, got {points.shape[2]}-D.")
    if trace is not None and not -points.shape[1] <= trace < points.shape[1]:
        raise ValueError(
            f"animate_chain: trace={trace} is not the index of one of the {points.shape[1]} points."
        )
    times = None if t is None else t[::every]
    drawn = np.stack([_with_ends(p, origin, closed) for p in points])
    created = ax is None
    ax, _ = _new_axes(ax)
    fig = ax.figure  # the root figure also when the axes is in a subfigure
    fig = cast("Figure", getattr(fig, "figure", None) or fig)
    low, high = drawn.min(axis=(0, 1)), drawn.max(axis=(0, 1))
    pad = 0.08 * max(float(np.max(high - low)), 1e-9)
    ax.set_xlim(low[0] - pad, high[0] + pad)
    ax.set_ylim(low[1] - pad, high[1] + pad)
    ax.set_aspect("equal")
    line = chain(points[0], ax=ax, origin=origin, closed=closed, **line_kwargs)
    (path_line,) = ax.plot([], [], lw=1, color="grey")

    def update(k):
        line.set_data(drawn[k, :, 0], drawn[k, :, 1])
        if trace is not None:
            path_line.set_data(points[: k + 1, trace, 0], points[: k + 1, trace, 1])
        if times is not None:
            ax.set_title(f"t = {times[k]:.2f}")
        return line, path_line

    anim = animate(fig, update, len(points), path, fps=fps, dpi=dpi)
    if created:
        _pyplot().close(fig)
    return anim
