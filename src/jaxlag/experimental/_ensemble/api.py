"""``jaxlag.experimental.simulate_ensemble``: the ensemble integrator's own entry point."""

from jax.sharding import Mesh, NamedSharding
from jaxtyping import PyTree
from typing_extensions import Unpack

from ..._batch.batch import simulate_batch
from ..._batch.ensemble import Ensemble, EnsembleBackend
from ..._custom_types import Args, RealArrayLike, SaveTimes, Validated
from ..._system import System
from ..._trajectory import Trajectory
from .options import EnsembleOptions, check_names


def simulate_ensemble(
    system: System,
    q0: RealArrayLike,
    qd0: RealArrayLike,
    ts: SaveTimes | None = None,
    *,
    args: Args = None,
    args_axes: PyTree[int | None] = None,
    sharding: Validated[str | Mesh | NamedSharding | None] = None,
    backend: Validated[EnsembleBackend] = "auto",
    **options: Unpack[EnsembleOptions],
) -> Trajectory:
    r"""A batch integrated as one explicit Runge–Kutta loop whose state is the whole batch,
    ``q, q̇`` of shape ``(B, n)``: each step is

        k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),   y₁ = y + h Σ b_i k_i,   e = h Σ b̂_i k_i

    with ``f(t, (q, q̇)) = (q̇, q̈)`` from ``M q̈ = F + Jᵀλ + Aᵀμ`` vmapped over the members and
    ``(c, a, b, b̂)`` the Butcher tableau of ``solver`` (an explicit Runge–Kutta method:
    ``diffrax.Tsit5()`` by default, ``diffrax.Dopri5()``, ``jl.RK4()``, ...), followed for
    constrained systems by ``projection``. Equal to
    ``jl.simulate_batch(..., method=jl.Ensemble(backend), ...)``.

    **Arguments:** ``system``, ``q0``, ``qd0``, ``ts``, ``args``, ``args_axes`` and
    ``sharding`` as for [`simulate_batch`][jaxlag.simulate_batch] (``ts`` may also be per member,
    ``(B, T)``); ``backend``: ``"xla"``, ``"pallas"`` (constant steps, one fused kernel),
    ``"pallas-interpret"`` or ``"auto"`` (``"xla"``); ``**options``: the options of
    [`simulate`][jaxlag.simulate] that the integrator supports (``t0``, ``t1``, ``solver``,
    ``stepsize_controller``, ``dt0``, ``saveat``, ``max_steps``, ``adjoint``, ``throw``,
    ``baumgarte``, ``projection``, ``checks``), with its defaults: ``stepsize_controller``
    ``diffrax.ConstantStepSize()`` (with ``dt0``, concrete save times) or
    ``diffrax.PIDController`` (each member its own step size), ``saveat`` at ``t1`` or at
    given times only, ``adjoint`` ``diffrax.RecursiveCheckpointAdjoint()`` (reverse mode, the
    default) or ``diffrax.ForwardMode()``. Events, unilateral constraints, friction and
    progress meters are not supported (the options ``events``, ``event`` and ``progress_meter``
    are a ``TypeError``): use [`simulate_batch`][jaxlag.simulate_batch] with ``method=jl.Vmap()``.

    Returns a [`Trajectory`][jaxlag.Trajectory] with a leading batch axis; ``throw=True`` raises
    [`SimulationError`][jaxlag.SimulationError] naming the first failed member.
    """
    check_names(options, "simulate_ensemble")
    return simulate_batch(
        system,
        q0,
        qd0,
        ts,
        args=args,
        args_axes=args_axes,
        sharding=sharding,
        method=Ensemble(backend),
        **options,
    )
