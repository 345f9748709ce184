r"""Learned accelerations without checks, and the losses of learned Lagrangians.

Every loss returns a `LossValue`: the mean over the members whose prediction is finite,
and the number of members that were not (an indefinite learned ``M = ∂²L/∂q̇²``, a rollout that
blew up, a row of the data that is not finite). Failed members are excluded from the mean and from
its gradient, never averaged in as NaN: one bad state does not poison the batch. Masking the
output alone would not do that: in the backward pass a zero cotangent times a non-finite partial
derivative is NaN (``0 · NaN``), and the weights are shared by all members. So the losses mask the
*inputs* of the computation too (the double ``where``): a failed member's row is replaced by a
finite row before any arithmetic, and its result by its target before the error is formed.
"""

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .. import _compile as compilation
from .._batch.batch import simulate_batch
from .._checks import Checks
from .._conventions import as_jit_inputs
from .._custom_types import Args, RealScalarLike
from .._mechanics import kkt as _kkt
from .._mechanics import lagrangian as _lagrangian
from .._mechanics.mass_solve import RobustSolve
from .._solver.rk4 import RK4
from .._system import System
from ._data import StateData, TrajectoryData, finite_rows, segments
from ._models import AbstractLagrangian

Model = AbstractLagrangian | System | Callable


def as_system(model: Model) -> System:
    """``model.system()`` for a learned model, the system itself, or ``jl.System(L)`` in learned
    mode (``mass_solve=jl.RobustSolve()``) for a function."""
    if isinstance(model, System):
        return model
    if isinstance(model, AbstractLagrangian):
        return model.system()
    return System(model, mass_solve=RobustSolve())


def accelerations(
    model: Model,
    q: Float[Array, " n"],
    qd: Float[Array, " n"],
    t: RealScalarLike = 0.0,
    args: Args = None,
) -> Float[Array, " n"]:
    r"""``q̈`` of ``M q̈ = F + Jᵀλ``, ``J q̈ = −γ`` for a learned model: NaN where it cannot be solved.

    The check-free path for training: no host callbacks and no eigen-decomposition, so it runs
    under ``jit``, ``vmap`` and ``grad`` and exports. The KKT system is solved with
    [`RobustSolve`][jaxlag.RobustSolve] (whatever ``mass_solve`` the model's system has): Cholesky of
    ``M = ∂²L/∂q̇²`` and of the Schur complement ``J M⁻¹ Jᵀ``, and a state whose pivots fall to
    ``rtol · max_i |M_ii|`` or below (``M`` indefinite or singular) gives NaN for that state
    alone, with a gradient of exactly zero (never NaN).
    ``model``: an `AbstractLagrangian`, a [`System`][jaxlag.System], or a function ``L``.
    Compiled once per model structure and shapes (the weights, states and ``args`` are inputs):
    an eager call, or an eager ``jax.vmap`` of it, runs one program, reused for new weights.
    """
    system = as_system(model)
    if not isinstance(system.mass_solve, RobustSolve):
        system = eqx.tree_at(lambda s: s.mass_solve, system, RobustSolve())
    q, qd = jnp.asarray(q), jnp.asarray(qd)
    t, args = as_jit_inputs(t, args, q.dtype if jnp.issubdtype(q.dtype, jnp.floating) else None)
    return _solved_accelerations(system, q, qd, t, args)


@compilation.filter_jit(cpu_options=False)
def _solved_accelerations(system, q, qd, t, args):
    """`accelerations`, one program per system (its arrays are inputs) and shapes: an eager call,
    or an eager ``jax.vmap`` of it, compiles once instead of one program per operation; inside a
    ``jit`` it is inlined."""
    t = _lagrangian.as_time(t, q)
    return _kkt.accelerations_and_multipliers(system, q, qd, t, args)[0]


class LossValue(eqx.Module):
    """A loss: ``value``, the mean over finite members, and ``failed``, the members left out."""

    value: Float[Array, ""]
    failed: Int[Array, ""]


def masked_mean(errors: Float[Array, " batch"], ok: Bool[Array, " batch"] | None = None) -> LossValue:
    """Mean of the finite ``errors`` at the members ``ok`` (``inf`` if there is none), and how many
    members were left out. The errors of the members left out must not come from non-finite
    arithmetic (mask the inputs first, see the module's docstring): the ``where`` here drops their
    value, not the NaN of their gradient."""
    ok = jnp.isfinite(errors) if ok is None else ok & jnp.isfinite(errors)
    count = jnp.sum(ok)
    total = jnp.sum(jnp.where(ok, errors, 0.0))
    value = jnp.where(count > 0, total / jnp.maximum(count, 1).astype(errors.dtype), jnp.inf)
    return LossValue(value, (errors.shape[0] - count).astype(jnp.int32))


def _scaled(error: Array, scale: Array | None) -> Array:
    return error if scale is None else error / jnp.broadcast_to(scale, error.shape)


@compilation.filter_jit(cpu_options=False)
def _loss_value(loss, model, data):
    """A built-in loss's value, one program per loss, model structure and data shapes (the
    model's weights and the data are its inputs): an eager call compiles once instead of one
    program per operation, and inside ``jit`` or ``grad`` (`train_step`) it is inlined."""
    return loss._value(model, data)


class AbstractLoss(eqx.Module):
    """A loss ``loss(model, data) -> LossValue`` (a Module: its options are fields).

    The built-in losses compile one program per loss, model structure and data shapes when
    called eagerly (inside ``jit`` or ``grad`` they are inlined); a subclass's ``__call__`` is
    called as written."""

    def __call__(self, model: Model, data: StateData | TrajectoryData) -> LossValue:
        raise NotImplementedError


class AccelerationLoss(AbstractLoss):
    r"""Mean over states of ``Σᵢ ((q̈ᵢ − q̈ᵢᵈᵃᵗᵃ) / scaleᵢ)²`` on `StateData`.

    ``q̈`` from `accelerations` (``M q̈ = F + Jᵀλ``); the data's known generalized forces
    ``StateData.forces`` (motor torques), if given, are part of ``F``. ``scale`` (n,): relative
    weights of the coordinates (``None``: 1), e.g. ``σ / rms(σ)`` with ``σ`` the standard deviation
    of the data's accelerations per coordinate, so that every coordinate weighs alike and the loss
    keeps the size of the plain mean squared error ([`Recipe.loss`][jaxlag.learned.Recipe.loss]).
    Dividing by ``σ`` itself also divides the loss and its gradient by ``rms(σ)²``, which can switch
    off a gradient clip tuned on the plain loss. States whose ``q̈`` is not finite, and rows of the
    data that are not (which `StateData` refuses when built eagerly, but not under ``jit``), are
    counted in ``failed`` and left out of the value and of the gradient. If every state fails the
    value is ``inf``.
    """

    scale: Float[Array, " n"] | None = None

    def __call__(self, model: Model, data: StateData) -> LossValue:  # pyright: ignore[reportIncompatibleMethodOverride]
        return _loss_value(self, model, data)

    def _value(self, model: Model, data: StateData) -> LossValue:
        # Rows of the data that are not finite are replaced by the first finite row before the
        # model sees them: the backward pass through them would be 0 · NaN (module docstring).
        ok = finite_rows(data.q, data.qd, data.qdd, data.forces)
        donor = jnp.argmax(ok)

        def safe(x):
            return jnp.where(ok[:, None], x, x[donor])

        q, qd, target = safe(data.q), safe(data.qd), safe(data.qdd)
        if data.forces is None:
            system = as_system(model)
            predicted = jax.vmap(lambda q, qd: accelerations(system, q, qd))(q, qd)
        else:
            system = _with_known_forces(model)
            predicted = jax.vmap(lambda q, qd, f: accelerations(system, q, qd, args=f))(
                q, qd, safe(data.forces)
            )
        # A state whose solve failed is NaN with a zero gradient (RobustSolve); it is replaced by
        # its target before the error is formed, so that no NaN enters the arithmetic either.
        ok = ok & finite_rows(predicted)
        predicted = jnp.where(ok[:, None], predicted, target)
        errors = jnp.sum(_scaled(predicted - target, self.scale) ** 2, axis=-1)
        return masked_mean(errors, ok)


def _known_forces(q, qd, args):
    return args


def _with_known_forces(model: Model) -> System:
    """The model's system with the sample's known generalized forces ``Q`` (passed as ``args``)."""
    if isinstance(model, AbstractLagrangian):
        return model.system(forces=_known_forces)
    if isinstance(model, System):
        raise TypeError(
            "StateData.forces (known generalized forces per sample) needs the model itself, not a "
            "jl.System: the loss adds the forces to the model's system."
        )
    return System(model, forces=_known_forces, mass_solve=RobustSolve())


class RolloutLoss(AbstractLoss):
    r"""Mean over trajectories and times of ``Σᵢ ((qᵢ(t) − qᵢᵈᵃᵗᵃ(t)) / scaleᵢ)²``.

    Each member of `TrajectoryData` is simulated with [`simulate_batch`][jaxlag.simulate_batch] from
    its first observed state; the models are autonomous, so all members share the first member's
    sample times relative to its start (sample every member alike). ``solver`` (default
    ``jl.RK4()``) takes constant steps ``dt0`` (``None``: the first sample spacing of the data
    divided by ``substeps``; ``max_steps`` bounds the steps of an explicit ``dt0``).
    ``velocities=True`` adds the same error on ``q̇``. A member whose rollout is not finite
    (``traj.failure.code != 0``) is counted in ``failed`` and left out of the value and of the
    gradient. Masking its outputs alone would not do: the backward pass through its steps after the
    failure multiplies zero cotangents by non-finite Jacobians (``0 · NaN``), and the weights are
    shared by all members. So the loss runs twice: a forward-only rollout finds the failed members,
    and the differentiated rollout starts each of them from the initial state of the first member
    that finished (an identical, finite copy, whose contribution is then masked). The gradient is
    exactly that of the finished members; the price is one more forward rollout. If every member
    fails, the value is ``inf`` and the gradient is not finite. Constrained models are projected
    back onto ``f = 0`` after every step (``jl.Projection()``, ``simulate``'s default).
    """

    solver: diffrax.AbstractSolver = RK4()
    dt0: float | None = None
    substeps: int = eqx.field(static=True, default=1)
    max_steps: int = eqx.field(static=True, default=4096)
    scale: Float[Array, " n"] | None = None
    velocities: bool = eqx.field(static=True, default=False)

    def rollout(
        self,
        model: Model,
        data: TrajectoryData,
        q0: Float[Array, "batch n"] | None = None,
        qd0: Float[Array, "batch n"] | None = None,
    ) -> tuple[Array, Array, Array]:
        """``(q, q̇, ok)``: the model's rollouts, shaped like ``data.q``, and which members finished
        with finite states (``traj.failure.code == 0``). They start from the first observed states
        of ``data``, or from ``q0``, ``qd0`` where given."""
        q0 = data.q[:, 0] if q0 is None else q0
        qd0 = data.qd[:, 0] if qd0 is None else qd0
        system = as_system(model)
        dt0 = self.dt0
        # Reverse mode through the solve needs a bound on the steps (diffrax's checkpoints).
        max_steps = self.max_steps
        if dt0 is None:
            dt0 = (data.ts[0, 1] - data.ts[0, 0]) / self.substeps
            max_steps = (data.ts.shape[1] - 1) * self.substeps + 4
        # Learned Lagrangians are autonomous: every member runs on the first member's times,
        # relative to its start (simulate_batch shares its save times across the batch).
        traj = simulate_batch(
            system,
            q0,
            qd0,
            data.ts[0] - data.ts[0, 0],
            solver=self.solver,
            stepsize_controller=diffrax.ConstantStepSize(),
            dt0=dt0,
            max_steps=max_steps,
            throw=False,
            checks=Checks(initial_state=False, times=False),
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
        )
        ok = jnp.all(jnp.isfinite(traj.q), axis=(1, 2)) & jnp.all(jnp.isfinite(traj.qd), axis=(1, 2))
        if traj.failure is not None:
            ok = ok & (traj.failure.code == 0)
        return traj.q, traj.qd, ok

    def __call__(self, model: Model, data: TrajectoryData) -> LossValue:  # pyright: ignore[reportIncompatibleMethodOverride]
        return _loss_value(self, model, data)

    def _value(self, model: Model, data: TrajectoryData) -> LossValue:
        # Members whose data are not finite (refused by TrajectoryData when built eagerly, not
        # under jit) fail too: their rows are replaced by a finite member's before any arithmetic.
        ok = finite_rows(data.q, data.qd)
        donor = jnp.argmax(ok)
        q0 = jnp.where(ok[:, None], data.q[:, 0], data.q[donor, 0])
        qd0 = jnp.where(ok[:, None], data.qd[:, 0], data.qd[donor, 0])
        # Forward only: which members fail. Then the differentiated rollout, with every failed
        # member restarted from the first finished member's initial state, so that no step of the
        # backward pass meets a non-finite state (see the class docstring).
        _, _, finished = jax.lax.stop_gradient(self.rollout(_without_gradient(model), data, q0, qd0))
        ok = ok & finished
        donor = jnp.argmax(ok)
        q0 = jnp.where(ok[:, None], data.q[:, 0], data.q[donor, 0])
        qd0 = jnp.where(ok[:, None], data.qd[:, 0], data.qd[donor, 0])
        q, qd, _ = self.rollout(model, data, q0, qd0)
        # Mask the copies' states and their targets before any arithmetic (their backward pass
        # then sees zeros).
        target_q = jnp.where(ok[:, None, None], data.q, data.q[donor])
        target_qd = jnp.where(ok[:, None, None], data.qd, data.qd[donor])
        q = jnp.where(ok[:, None, None], q, target_q)
        qd = jnp.where(ok[:, None, None], qd, target_qd)
        errors = jnp.sum(_scaled(q - target_q, self.scale) ** 2, axis=-1)
        if self.velocities:
            errors = errors + jnp.sum(_scaled(qd - target_qd, self.scale) ** 2, axis=-1)
        return masked_mean(jnp.mean(errors, axis=1), ok)


def _without_gradient(tree):
    """``tree`` with ``lax.stop_gradient`` on its arrays (a model's functions pass through)."""
    return jax.tree_util.tree_map(lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, tree)


class MultipleShootingLoss(AbstractLoss):
    r"""A `RolloutLoss` on short segments of the data, each started from its observed state.

    The trajectories are cut into segments of ``length`` samples (`segments`); every
    segment is simulated from its own first observed ``(q, q̇)``. Short segments keep the loss
    smooth in the weights where one long rollout of a chaotic system is not.
    """

    length: int = eqx.field(static=True, default=5)
    rollout: RolloutLoss = RolloutLoss()

    def __call__(self, model: Model, data: TrajectoryData) -> LossValue:  # pyright: ignore[reportIncompatibleMethodOverride]
        return _loss_value(self, model, data)

    def _value(self, model: Model, data: TrajectoryData) -> LossValue:
        return self.rollout._value(model, segments(data, self.length))


def state_data(model: Model, data: TrajectoryData, args: Args = None) -> StateData:
    """The states of ``data`` with the accelerations of a known ``model`` (e.g. a ready system):
    ``state_data(model, data)``, the model first."""
    if isinstance(model, (TrajectoryData, StateData)) or not isinstance(data, TrajectoryData):
        raise TypeError(
            "state_data(model, data) takes the model (a jl.System, a learned model or a function "
            "L(q, qd)) first and the TrajectoryData second; got "
            f"({type(model).__name__}, {type(data).__name__})"
            + (": swap the arguments." if isinstance(model, TrajectoryData) else ".")
        )
    n = data.q.shape[-1]
    q, qd = data.q.reshape(-1, n), data.qd.reshape(-1, n)
    system = as_system(model)
    qdd = jax.vmap(lambda a, b: accelerations(system, a, b, args=args))(q, qd)
    return StateData(q, qd, qdd)
