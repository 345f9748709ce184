r"""Spatial algebra (Featherstone's 6-vectors), batched over leading axes.

A spatial motion vector is ``m = (ω, v)``: the angular velocity and the velocity of the body
point at the frame's origin, both in the frame's components. A spatial force is ``f = (n, f)``:
the moment about the frame's origin and the force. A frame's pose in another is ``(R, p)``:
``R`` maps the frame's components to the other's, ``p`` is the frame's origin in the other's
coordinates. The motion transform from the outer frame to the inner one is

``X = [[Rᵀ, 0], [−Rᵀ[p]ₓ, Rᵀ]]``,

and ``Xᵀ`` carries a spatial force from the inner frame back to the outer one. Every function
takes arrays with any leading batch axes (``...``).
"""

import jax.numpy as jnp
from jaxtyping import Array, Float


def skew(w: Float[Array, "*b 3"]) -> Float[Array, "*b 3 3"]:
    """``[w]ₓ``, the matrix of ``x ↦ w × x``."""
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    zero = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def quaternion_rotation(quaternion: Float[Array, "*b 4"]) -> Float[Array, "*b 3 3"]:
    """The rotation of the quaternion ``(w, x, y, z)``, normalized first (as MuJoCo does)."""
    unit = quaternion / jnp.linalg.norm(quaternion, axis=-1, keepdims=True)
    w, x, y, z = unit[..., 0], unit[..., 1], unit[..., 2], unit[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def axis_angle_rotation(axis: Float[Array, "*b 3"], angle: Float[Array, "*b"]) -> Float[Array, "*b 3 3"]:
    """Rodrigues: ``R = I + sin θ [a]ₓ + (1 − cos θ)[a]ₓ²`` for a unit axis ``a``."""
    k = skew(axis)
    s = jnp.sin(angle)[..., None, None]
    c = jnp.cos(angle)[..., None, None]
    return jnp.broadcast_to(jnp.eye(3, dtype=axis.dtype), k.shape) + s * k + (1 - c) * (k @ k)


def motion_transform(
    rotation: Float[Array, "*b 3 3"], translation: Float[Array, "*b 3"]
) -> Float[Array, "*b 6 6"]:
    """``X = [[Rᵀ, 0], [−Rᵀ[p]ₓ, Rᵀ]]``: motion vectors from the outer frame to the frame at
    ``(R, p)`` in it."""
    rt = jnp.swapaxes(rotation, -1, -2)
    zero = jnp.zeros_like(rt)
    top = jnp.concatenate([rt, zero], axis=-1)
    bottom = jnp.concatenate([-rt @ skew(translation), rt], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


def inverse_motion_transform(
    rotation: Float[Array, "*b 3 3"], translation: Float[Array, "*b 3"]
) -> Float[Array, "*b 6 6"]:
    """``X⁻¹ = [[R, 0], [[p]ₓR, R]]``: motion vectors from the frame at ``(R, p)`` to the outer one."""
    zero = jnp.zeros_like(rotation)
    top = jnp.concatenate([rotation, zero], axis=-1)
    bottom = jnp.concatenate([skew(translation) @ rotation, rotation], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


def motion_cross(m: Float[Array, "*b 6"]) -> Float[Array, "*b 6 6"]:
    """``m ×`` on motion vectors: ``[[ω×, 0], [v×, ω×]]``."""
    w = skew(m[..., :3])
    v = skew(m[..., 3:])
    zero = jnp.zeros_like(w)
    return jnp.concatenate(
        [jnp.concatenate([w, zero], axis=-1), jnp.concatenate([v, w], axis=-1)],
        axis=-2,
    )


def force_cross(m: Float[Array, "*b 6"]) -> Float[Array, "*b 6 6"]:
    """``m ×*`` on force vectors: ``−(m ×)ᵀ = [[ω×, v×], [0, ω×]]``."""
    return -jnp.swapaxes(motion_cross(m), -1, -2)


def spatial_inertia(
    mass: Float[Array, "*b"], com: Float[Array, "*b 3"], inertia: Float[Array, "*b 3 3"]
) -> Float[Array, "*b 6 6"]:
    """The 6 × 6 inertia at the frame's origin of a body of mass ``m``, centre of mass ``c`` and
    rotational inertia ``I_c`` about it: ``[[I_c + m[c]ₓ[c]ₓᵀ, m[c]ₓ], [m[c]ₓᵀ, m 1]]``."""
    c = skew(com)
    m = mass[..., None, None]
    ct = jnp.swapaxes(c, -1, -2)
    top = jnp.concatenate([inertia + m * (c @ ct), m * c], axis=-1)
    bottom = jnp.concatenate([m * ct, m * jnp.broadcast_to(jnp.eye(3, dtype=com.dtype), c.shape)], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)
