r"""Learned Lagrangians: LNN, DeLaN and constrained (Cartesian) LNNs, trained with optax.

Models are equinox Modules callable as ``L(q, q̇)``; ``model.system()`` is the
[`System`][jaxlag.System] that simulates them (``M q̈ = F + Jᵀλ``, ``M = ∂²L/∂q̇²``, ``J = ∂f/∂q``
for the known constraints of `ConstrainedLagrangian`). Losses return a
`LossValue` that counts the members whose prediction is not finite instead of averaging
NaN in; `train_step` is one pure optax step and `train` a loop with validation, early
stopping and guards around it (data refused by name, non-finite steps skipped and reported);
`train_recipe` trains with the benchmark's `Recipe`.
"""

from ._data import (
    StateData as StateData,
)
from ._data import (
    TrajectoryData as TrajectoryData,
)
from ._data import (
    segments as segments,
)
from ._data import (
    split as split,
)
from ._losses import (
    AbstractLoss as AbstractLoss,
)
from ._losses import (
    AccelerationLoss as AccelerationLoss,
)
from ._losses import (
    LossValue as LossValue,
)
from ._losses import (
    MultipleShootingLoss as MultipleShootingLoss,
)
from ._losses import (
    RolloutLoss as RolloutLoss,
)
from ._losses import (
    accelerations as accelerations,
)
from ._losses import (
    state_data as state_data,
)
from ._models import (
    AbstractLagrangian as AbstractLagrangian,
)
from ._models import (
    AngleEmbedding as AngleEmbedding,
)
from ._models import (
    ConstrainedLagrangian as ConstrainedLagrangian,
)
from ._models import (
    DeLaN as DeLaN,
)
from ._models import (
    MLPLagrangian as MLPLagrangian,
)
from ._recipe import Recipe as Recipe
from ._recipe import RecipeResult as RecipeResult
from ._recipe import train_recipe as train_recipe
from ._training import TrainResult as TrainResult
from ._training import train as train
from ._training import train_step as train_step

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
    "Recipe",
    "RecipeResult",
    "RolloutLoss",
    "StateData",
    "TrainResult",
    "TrajectoryData",
    "accelerations",
    "segments",
    "split",
    "state_data",
    "train",
    "train_recipe",
    "train_step",
]
