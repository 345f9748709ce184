"""Ready-made, documented models: each function returns a [`jaxlag.System`][jaxlag.System].

Parameters are read from ``args``, a dict whose missing keys take the model's defaults
(``model.defaults``; `default_args` gives an editable copy), so ``args=None`` simulates the
default model and ``jax.grad`` flows through any parameter you pass. Unknown keys are an error.
Each docstring states the coordinates, the constraints (and the meaning of their multipliers)
and the closed forms the model is tested against.

=====================================  =========================================================
model                                   forms / coordinates
=====================================  =========================================================
`simple_pendulum`                 ``(θ,)`` generalized; ``(x, y)`` Cartesian
`double_pendulum`                 ``(θ₁, θ₂)``; ``(x₁, y₁, x₂, y₂)``
`n_link_pendulum`                 ``(θ₁..θ_n)``; ``(x₁, y₁, …)``
`spherical_pendulum`              ``(θ, φ)``; ``(x, y, z)``
`free_chain`                      ``(x₁, …, x_n)`` with rigid links, 2-D or 3-D
`cart_pole`                       ``(x, θ)`` with an input force on the cart
`bead_on_hoop`                    ``(θ,)``; ``(x, y, z)``; optionally spinning
`bead_on_rotating_parabola`       ``(r,)``; ``(r, φ, z)`` with a rheonomic drive
`particle_on_cone`                ``(r, φ)``; ``(r, θ, φ)``; ``(x, y, z)``
`particle_on_sphere`              ``(r, θ, φ)``; ``(x, y, z)``; optionally one-sided
`spiral`                          ``(r, θ)`` on ``r = aθ``; ``(θ,)``
`kepler`                          ``(r, φ)``; ``(x, y)``
`charged_particle`                ``(x, y, z)`` in uniform ``E``, ``B``
`rolling_disk`                    ``(x, y, φ, θ)``, nonholonomic
`disk_on_incline`                 ``(s, θ)`` with the rolling constraint ``s = Rθ``
`knife_edge`                      ``(x, y, θ)``, nonholonomic, on an incline
`heavy_top`                       ``(φ, θ, ψ)`` Euler; quaternion; the nine entries of R
`torque_free_body`                ``(φ, θ, ψ)``; quaternion; nine entries of R
`gyroscope`                       ``(α, β, γ)``: outer gimbal, inner gimbal, rotor
`rolling_disk_3d`                 ``(x, y, z, φ, θ, ψ)``, contact + rolling, leans and steers
`ball_on_turntable`               ``(x, y)`` and a quaternion, rolling on a moving table
`whipple_bicycle`                 ``(x, y, ψ, φ, θ, δ, θ_R, θ_F)``: four bodies, two rolling
                                        wheels (benchmark of Meijaard et al. 2007)
`robot_arm`                       six hinges read from MJCF (``jaxlag.robots``), six motors
`space_robot`                     a free-flying base (position, quaternion) and two arms
=====================================  =========================================================
"""

from ._bicycle import bicycle_eigenvalues, bicycle_upright_state, whipple_bicycle
from ._common import default_args
from ._fields import charged_particle, kepler
from ._pendulums import (
    cart_pole,
    double_pendulum,
    free_chain,
    n_link_pendulum,
    simple_pendulum,
    spherical_pendulum,
)
from ._rigid import ball_on_turntable, gyroscope, heavy_top, rolling_disk_3d, torque_free_body
from ._robots import robot_arm, space_robot
from ._rolling import disk_on_incline, knife_edge, rolling_disk
from ._surfaces import (
    bead_on_hoop,
    bead_on_rotating_parabola,
    particle_on_cone,
    particle_on_sphere,
    spiral,
)

__all__ = [
    "ball_on_turntable",
    "bead_on_hoop",
    "bead_on_rotating_parabola",
    "bicycle_eigenvalues",
    "bicycle_upright_state",
    "cart_pole",
    "charged_particle",
    "default_args",
    "disk_on_incline",
    "double_pendulum",
    "free_chain",
    "gyroscope",
    "heavy_top",
    "kepler",
    "knife_edge",
    "n_link_pendulum",
    "particle_on_cone",
    "particle_on_sphere",
    "robot_arm",
    "rolling_disk",
    "rolling_disk_3d",
    "simple_pendulum",
    "space_robot",
    "spherical_pendulum",
    "spiral",
    "torque_free_body",
    "whipple_bicycle",
]
