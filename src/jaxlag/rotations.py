r"""Rotations in space: matrices from Euler angles, quaternions and axis–angle; angular velocity.

Conventions (used throughout jaxlag):

* ``R`` (3 × 3) maps body components to world components: a vector with body components ``r``
  has world components ``R r``. A rotation by ``angle`` about a unit ``axis`` is
  right-handed (counter-clockwise looking down the axis).
* Euler angles ``(a₁, a₂, a₃)`` with a sequence such as ``"zxz"`` are **intrinsic** by default
  (each rotation about an axis of the already rotated frame): ``R = R_{s₁}(a₁) R_{s₂}(a₂)
  R_{s₃}(a₃)``. ``extrinsic=True`` rotates about the fixed world axes instead:
  ``R = R_{s₃}(a₃) R_{s₂}(a₂) R_{s₁}(a₁)``. Any sequence of three letters from ``xyz`` with no
  two neighbours equal is accepted: ``"zxz"`` (classical mechanics: precession, nutation,
  spin), ``"zyx"`` (yaw, pitch, roll), ``"xyz"``, ``"zyz"``, ...
* Quaternions are ``(w, x, y, z)``, scalar first. `quaternion_matrix` uses the quadratic
  form ``R = (w² − v·v) I + 2 v vᵀ + 2 w [v]ₓ`` without normalizing: for a unit quaternion it is
  the rotation; off the unit sphere it is ``|q|²`` times a rotation, so a Lagrangian in terms of
  it keeps a positive-definite mass matrix and ``|q|² = 1`` can be a holonomic constraint.
* Angular velocity: ``[ω_body]ₓ = RᵀṘ`` and ``[ω_world]ₓ = Ṙ Rᵀ``, ``ω_world = R ω_body``.
  `angular_velocity` forms ``Ṙ = (∂R/∂q) q̇ + ∂R/∂t`` by one ``jax.jvp`` of the
  orientation map along ``(q̇, 1)``; the vector is read off the skew part (exact when ``R`` is
  orthogonal).

Singularities (where a parametrization loses rank: the map from coordinate rates to ``ω``
drops from rank 3 to 2, so the mass matrix of a body described by it is singular there):

=================================  ==========================================  =====================
parametrization                     singular at                                 fix
=================================  ==========================================  =====================
proper Euler (``"zxz"``, ``"zyz"``,  middle angle ``a₂ = 0`` or ``π``                a quaternion body, or
``"xyx"``, ... first = last)        (``θ = 0, π`` for ``"zxz"``)                 start away from it
Tait–Bryan (``"zyx"``, ``"xyz"``,   middle angle ``a₂ = ±π/2`` (pitch ±90°       same
... three different axes)           for yaw–pitch–roll)
quaternion + ``|q|² = 1``           nowhere (``q`` and ``−q`` are one rotation)   —
nine entries of ``R`` + ``RᵀR = I``   nowhere                                      —
=================================  ==========================================  =====================

`gimbal_lock_margin` measures the distance to the Euler singularity (``|sin a₂|`` or
``|cos a₂|``, 0 at gimbal lock).
"""

import contextlib
import contextvars
from collections.abc import Callable, Iterator
from typing import cast

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._conventions import wrap_configuration_function
from ._custom_types import Args, Coordinates, RealScalarLike, Validated, Velocities

__all__ = [
    "angular_velocity",
    "axis_angle_matrix",
    "axis_rotation",
    "euler_matrix",
    "gimbal_lock_margin",
    "quaternion_from_matrix",
    "quaternion_matrix",
    "skew",
    "unskew",
]

_AXES = {"x": 0, "y": 1, "z": 2}

# Set only while jaxlag diagnoses a singular mass matrix at the initial state (an eager call on
# the failure path): euler_matrix then records its sequence and angles so that the message can
# name the gimbal lock. Never set while a user's program is traced or run.
_EULER_CALLS: contextvars.ContextVar[list | None] = contextvars.ContextVar("jaxlag_euler_calls", default=None)


@contextlib.contextmanager
def record_euler_calls() -> Iterator[list]:
    """Within the block, `euler_matrix` appends ``(sequence, extrinsic, angles)`` to the
    yielded list (private: used by the diagnosis of coordinate singularities)."""
    calls: list = []
    token = _EULER_CALLS.set(calls)
    try:
        yield calls
    finally:
        _EULER_CALLS.reset(token)


def _check_sequence(sequence) -> None:
    if (
        not isinstance(sequence, str)
        or len(sequence) != 3
        or any(a not in _AXES for a in sequence)
        or sequence[0] == sequence[1]
        or sequence[1] == sequence[2]
    ):
        raise ValueError(
            f"sequence must be three letters from 'xyz' with no two neighbours equal (e.g. 'zxz', "
            f"'zyx'); got {sequence!r}."
        )


def euler_singularity(sequence: str) -> str:
    """Where the Euler angles of ``sequence`` are singular, in words (for messages and docs)."""
    _check_sequence(sequence)
    if sequence[0] == sequence[2]:
        return "the middle angle a₂ = 0 or π (proper Euler angles: a₁ and a₃ then turn about the same axis)"
    return "the middle angle a₂ = ±π/2 (Tait–Bryan angles: a₁ and a₃ then turn about the same axis)"


def gimbal_lock_margin(angles: Validated[Float[ArrayLike, "3"]], sequence: str = "zxz") -> Float[Array, ""]:
    """Distance of the Euler angles ``(a₁, a₂, a₃)`` from gimbal lock: ``|sin a₂|`` for proper
    Euler sequences (first axis = last, singular at ``a₂ = 0, π``), ``|cos a₂|`` for
    Tait–Bryan sequences (singular at ``a₂ = ±π/2``). It vanishes exactly where the map from
    angle rates to angular velocity loses rank, where the mass matrix of a body described by
    these angles alone is singular. Use it as an event condition to stop
    before the singularity, or switch to a quaternion body, which has none."""
    _check_sequence(sequence)
    angles = _float(angles)
    if angles.shape != (3,):
        raise ValueError(f"gimbal_lock_margin takes three angles, shape (3,); got shape {angles.shape}.")
    middle = angles[1]
    return jnp.abs(jnp.sin(middle)) if sequence[0] == sequence[2] else jnp.abs(jnp.cos(middle))


def _float(x):
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    return x


def skew(vector: Validated[Float[ArrayLike, "3"]]) -> Float[Array, "3 3"]:
    """``[v]ₓ``, the matrix with ``[v]ₓ r = v × r``."""
    v = _float(vector)
    if v.shape != (3,):
        raise ValueError(f"skew expects a vector of shape (3,); got shape {v.shape}.")
    zero = jnp.zeros((), v.dtype)
    return jnp.stack(
        [
            jnp.stack([zero, -v[2], v[1]]),
            jnp.stack([v[2], zero, -v[0]]),
            jnp.stack([-v[1], v[0], zero]),
        ]
    )


def unskew(matrix: Validated[Float[ArrayLike, "3 3"]]) -> Float[Array, "3"]:
    """The vector ``v`` of the skew part of ``W``: ``½(W − Wᵀ) = [v]ₓ`` (inverse of `skew`)."""
    w = _float(matrix)
    if w.shape != (3, 3):
        raise ValueError(f"unskew expects a matrix of shape (3, 3); got shape {w.shape}.")
    return 0.5 * jnp.stack([w[2, 1] - w[1, 2], w[0, 2] - w[2, 0], w[1, 0] - w[0, 1]])


def axis_rotation(axis: str, angle: Validated[RealScalarLike]) -> Float[Array, "3 3"]:
    """Rotation by ``angle`` about the coordinate axis ``"x"``, ``"y"`` or ``"z"``:
    ``R = I + sin a K + (1 − cos a) K²`` with the constant generator ``K = [e]ₓ`` (few operations,
    which keeps the traced graphs of long chains of rotations small)."""
    if axis not in _AXES:
        raise ValueError(f"axis must be 'x', 'y' or 'z'; got {axis!r}.")
    angle = _float(angle)
    if angle.shape != ():
        raise ValueError(f"axis_rotation takes a scalar angle; got shape {angle.shape}.")
    generator = np.zeros((3, 3))
    i = _AXES[axis]
    j, k = (i + 1) % 3, (i + 2) % 3
    generator[k, j], generator[j, k] = 1.0, -1.0
    square = generator @ generator
    rotation = np.eye(3) + jnp.sin(angle) * generator + (1.0 - jnp.cos(angle)) * square
    return cast(Array, rotation).astype(angle.dtype)  # NumPy defers to the JAX array: an Array


def euler_matrix(
    angles: Validated[Float[ArrayLike, "3"]], sequence: str = "zxz", *, extrinsic: bool = False
) -> Float[Array, "3 3"]:
    """Rotation matrix (body → world) from three Euler angles.

    ``sequence``: three letters from ``xyz``, neighbours different (``"zxz"``, ``"zyx"``, ...).
    Intrinsic (default): ``R = R_{s₁}(a₁) R_{s₂}(a₂) R_{s₃}(a₃)``; extrinsic:
    ``R = R_{s₃}(a₃) R_{s₂}(a₂) R_{s₁}(a₁)``. ``"zyx"`` intrinsic is yaw–pitch–roll; ``"zxz"``
    is the classical ``(φ, θ, ψ)`` = (precession, nutation, spin), singular (gimbal lock) at
    ``θ = 0, π``; every proper sequence (first axis = last) is singular at ``a₂ = 0, π``, every
    Tait–Bryan sequence (``"zyx"``: pitch) at ``a₂ = ±π/2`` (`gimbal_lock_margin`).
    """
    _check_sequence(sequence)
    angles = _float(angles)
    if angles.shape != (3,):
        raise ValueError(f"euler_matrix takes three angles, shape (3,); got shape {angles.shape}.")
    calls = _EULER_CALLS.get()
    if calls is not None:
        calls.append((sequence, extrinsic, angles))
    factors = [axis_rotation(a, angles[i]) for i, a in enumerate(sequence)]
    if extrinsic:
        factors = factors[::-1]
    return factors[0] @ factors[1] @ factors[2]


def quaternion_matrix(quaternion: Validated[Float[ArrayLike, "4"]]) -> Float[Array, "3 3"]:
    r"""``R = (w² − v·v) I + 2 v vᵀ + 2 w [v]ₓ`` for ``q = (w, v)``, scalar first.

    The rotation for a unit quaternion. Deliberately not normalized: for ``q = s u`` (``u``
    unit) it is ``s² R(u)``, so scaling ``q`` changes ``R`` and a kinetic energy built on it
    (see [`jaxlag.coordinates.RigidBody3D`][jaxlag.coordinates.RigidBody3D]) stays positive definite in all
    four
    directions. Impose ``q·q − 1 = 0`` as a holonomic constraint.
    """
    q = _float(quaternion)
    if q.shape != (4,):
        raise ValueError(f"quaternion_matrix takes (w, x, y, z), shape (4,); got shape {q.shape}.")
    w, v = q[0], q[1:]
    eye = jnp.eye(3, dtype=q.dtype)
    return (w * w - v @ v) * eye + 2.0 * jnp.outer(v, v) + 2.0 * w * skew(v)


def quaternion_from_matrix(matrix: Validated[Float[ArrayLike, "3 3"]]) -> Float[Array, "4"]:
    """The unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd's method: the
    best-conditioned of the four formulas, chosen without branching, so ``jit`` and ``grad``
    work). ``q`` and ``−q`` are the same rotation; the one returned has its largest component
    positive."""
    r = _float(matrix)
    if r.shape != (3, 3):
        raise ValueError(f"quaternion_from_matrix takes a (3, 3) matrix; got shape {r.shape}.")
    d0, d1, d2 = r[0, 0], r[1, 1], r[2, 2]
    candidates = jnp.stack(
        [
            jnp.stack([1.0 + d0 + d1 + d2, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]),
            jnp.stack([r[2, 1] - r[1, 2], 1.0 + d0 - d1 - d2, r[0, 1] + r[1, 0], r[0, 2] + r[2, 0]]),
            jnp.stack([r[0, 2] - r[2, 0], r[0, 1] + r[1, 0], 1.0 - d0 + d1 - d2, r[1, 2] + r[2, 1]]),
            jnp.stack([r[1, 0] - r[0, 1], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1], 1.0 - d0 - d1 + d2]),
        ]
    )
    pivots = jnp.diagonal(candidates)
    best = jnp.argmax(pivots)
    pivot = jnp.maximum(pivots[best], jnp.finfo(r.dtype).tiny)
    return candidates[best] * (0.5 / jnp.sqrt(pivot))


def axis_angle_matrix(
    axis: Validated[Float[ArrayLike, "3"]], angle: Validated[RealScalarLike]
) -> Float[Array, "3 3"]:
    r"""Rodrigues' formula: ``R = I + sin a [n]ₓ + (1 − cos a) [n]ₓ²`` about the unit vector
    ``n = axis/|axis|``."""
    axis = _float(axis)
    if axis.shape != (3,):
        raise ValueError(f"axis_angle_matrix takes an axis of shape (3,); got shape {axis.shape}.")
    angle = _float(angle)
    if angle.shape != ():
        raise ValueError(f"axis_angle_matrix takes a scalar angle; got shape {angle.shape}.")
    n = axis / jnp.linalg.norm(axis)
    k = skew(n)
    return jnp.eye(3, dtype=k.dtype) + jnp.sin(angle) * k + (1.0 - jnp.cos(angle)) * (k @ k)


def _orientation_rate(orientation, q, qd, t, args):
    """``(R, Ṙ)`` with ``Ṙ = (∂R/∂q) q̇ + ∂R/∂t``: one jvp along ``(q̇, 1)``."""
    t = jnp.asarray(t, dtype=q.dtype)
    return jax.jvp(lambda x, s: jnp.asarray(orientation(x, t=s, args=args)), (q, t), (qd, jnp.ones_like(t)))


def angular_velocity(
    orientation: Callable,
    q: Coordinates,
    qd: Velocities,
    t: RealScalarLike = 0.0,
    args: Args = None,
    *,
    frame: str = "body",
) -> Float[Array, "3"]:
    """Angular velocity of the frame ``R(q, [t], [args])`` (body → world), in body or world axes.

    ``frame="body"``: ``ω = vee(RᵀṘ)``; ``frame="world"``: ``ω = vee(Ṙ Rᵀ) = R ω_body``.
    ``orientation`` follows the calling convention (``t`` and ``args`` by keyword if declared)
    and may return a ``(3, 3)`` matrix; ``Ṙ`` comes from one ``jax.jvp`` along ``(q̇, 1)``.
    """
    if frame not in ("body", "world"):
        raise ValueError(f"frame must be 'body' or 'world'; got {frame!r}.")
    fn = wrap_configuration_function(orientation, "orientation map")
    q, qd = _float(q), _float(qd)
    rotation, rate = _orientation_rate(fn, q, qd, t, args)
    if rotation.shape != (3, 3):
        raise ValueError(
            f"The orientation map must return a rotation matrix of shape (3, 3); it returned shape "
            f"{rotation.shape}."
        )
    if frame == "body":
        return unskew(rotation.T @ rate)
    return unskew(rate @ rotation.T)
