r"""Learned Lagrangians: LNN, DeLaN and constrained (Cartesian) LNNs, trained with optax.

Models are equinox Modules callable as ``L(q, q̇)``; ``model.system()`` is the
:class:`~jaxlag.System` that simulates them (``M q̈ = F + Jᵀλ``, ``M = ∂²L/∂q̇²``, ``J = ∂f/∂q``
for the known constraints of :class:`ConstrainedLagrangian`). Losses return a
:class:`LossValue` that counts the members whose prediction is not finite instead of averaging
NaN in; :func:`train_step` is one pure optax step and :func:`train` a loop with validation and
early stopping around it.
"""

from ._data import (
    StateData as StateData,
    TrajectoryData as TrajectoryData,
    segments as segments,
    split as split,
)
from ._losses import (
    AbstractLoss as AbstractLoss,
    AccelerationLoss as AccelerationLoss,
    LossValue as LossValue,
    MultipleShootingLoss as MultipleShootingLoss,
    RolloutLoss as RolloutLoss,
    accelerations as accelerations,
    state_data as state_data,
)
from ._models import (
    AbstractLagrangian as AbstractLagrangian,
    AngleEmbedding as AngleEmbedding,
    ConstrainedLagrangian as ConstrainedLagrangian,
    DeLaN as DeLaN,
    MLPLagrangian as MLPLagrangian,
)
from ._training import TrainResult as TrainResult, train as train, train_step as train_step

__all__ = [
    "AbstractLagrangian",
    "AbstractLoss",
    "AccelerationLoss",
    "AngleEmbedding",
    "ConstrainedLagrangian",
    "DeLaN",
    "LossValue",
    "MLPLagrangian",
    "MultipleShootingLoss",
    "RolloutLoss",
    "StateData",
    "TrainResult",
    "TrajectoryData",
    "accelerations",
    "segments",
    "split",
    "state_data",
    "train",
    "train_step",
]
