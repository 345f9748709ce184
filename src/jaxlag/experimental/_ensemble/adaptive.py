r"""Adaptive steps (``diffrax.PIDController``): every member has its own ``t`` and step size ``h``.

Steps are clipped to land on the member's next save time; the step-size control is diffrax's
(`jaxlag.experimental._ensemble.controller`). Finished members are masked; the loop stops when
every member has reached its last save time or failed: a member whose step is rejected at
round-off size (``≤ 64 ε max(|t|, t₁ − t₀)``) stops there, as ``jl.simulate``'s guard stops
diffrax (non-finite trial state: code 1; finite: the step size collapsed, code 5).

The loop is ``equinox.internal.while_loop``: ``kind="checkpointed"`` (reverse mode, memory
``O(log steps)``) with the default ``adjoint=diffrax.RecursiveCheckpointAdjoint()``,
``kind="lax"`` (forward mode) with ``adjoint=diffrax.ForwardMode()``, as in diffrax. The saved
states are the loop's write-only buffers: every member writes once per iteration (one batched
scatter), into its next save column when it lands on a save time and into a spare column
otherwise, so checkpoints never copy them.

One iteration is a pipeline over named Modules: `AdaptiveLoop.attempt` (a `Trial` step of
every member), `error_norm` and `propose_step` (the controller's `StepProposal`), then
`AdaptiveLoop.advance` (the next `AdaptiveState`, the saves written).
"""

import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..._errors import FailureCode
from ..._solver.guard import _ULPS
from .controller import ControllerState, StepProposal, bounded, error_norm, initial_step, propose_step
from .outcome import LoopRecord
from .settings import EnsembleSettings
from .step import BatchedField, rk_step, select

__all__ = ["AdaptiveState", "Trial", "AdaptiveLoop"]

State = tuple[Float[Array, "batch n"], Float[Array, "batch n"]]
# Inside the checkpointed while loop the saves are equinox's write-only buffers over the arrays.
Saves = tuple[
    eqxi.MaybeBuffer[Float[Array, "batch saves n"]], eqxi.MaybeBuffer[Float[Array, "batch saves n"]]
]


class AdaptiveState(eqx.Module):
    """The adaptive loop's carry, every entry per member (leading axis ``B``): time ``t``, the
    next step ``dt`` to try, the state ``y = (q, q̇)``, the last stage ``f = f(t, y)`` for
    first-same-as-last tableaus (else ``None``), the next save column ``k``, the save buffers
    (``(B, T + 1, n)`` each, the last column a spare), the controller's memory, the step
    counts, whether the member failed (and with a non-finite trial state) and the last step
    tried."""

    t: Float[Array, " batch"]
    dt: Float[Array, " batch"]
    y: State
    f: State | None
    k: Int[Array, " batch"]
    saves: Saves
    control: ControllerState
    accepted: Int[Array, " batch"]
    rejected: Int[Array, " batch"]
    failed: Bool[Array, " batch"]
    nonfinite: Bool[Array, " batch"]
    last_dt: Float[Array, " batch"]


class Trial(eqx.Module):
    """One iteration's step of every member: whether the member is still ``running``, whether
    its step was ``clipped`` onto its next save time, the step ``h`` from ``t`` to ``t1``, the
    trial state ``y1`` (not yet projected), the error estimate and the last stage."""

    running: Bool[Array, " batch"]
    clipped: Bool[Array, " batch"]
    h: Float[Array, " batch"]
    t1: Float[Array, " batch"]
    y1: State
    error: State
    f_last: State | None


def _write_saves(saves: Saves, k, save, y1, num_saves: int) -> Saves:
    """Every member writes every iteration (one batched scatter), those not saving into the
    spare last column, which is never read. (An out-of-range index with mode="drop" would do the
    same forward, but the checkpointed loop's reverse pass gathers the cotangent at that index,
    and an out-of-range gather fills with NaN.)"""
    members = jnp.arange(k.shape[0])
    index = jnp.where(save, k, num_saves)
    return saves[0].at[members, index].set(y1[0]), saves[1].at[members, index].set(y1[1])


class AdaptiveLoop(eqx.Module):
    """The adaptive loop of a batch: its field, settings and save times ``ts`` (B, T), the first
    column the start times."""

    field: BatchedField
    settings: EnsembleSettings
    ts: Float[Array, "batch times"]

    @property
    def num_saves(self) -> int:
        return self.ts.shape[1]

    def tiny_step(self):
        """A rejected step this small (per member) is at round-off: the member stops."""
        ts = self.ts
        scale = jnp.maximum(jnp.max(jnp.abs(ts), axis=1), ts[:, -1] - ts[:, 0])
        return _ULPS * float(jnp.finfo(ts.dtype).eps) * scale

    def init(self, y0: State, dt0) -> AdaptiveState:
        batch, n = y0[0].shape
        t0 = self.ts[:, 0]
        f0 = self.field(t0, y0)
        if dt0 is None:
            dt = initial_step(self.field, self.settings, t0, y0, f0)
        else:
            dt = jnp.broadcast_to(jnp.asarray(dt0, self.ts.dtype), (batch,))
        dt = bounded(self.settings, dt)
        # One spare column: members that do not save this iteration write there.
        shape = (batch, self.num_saves + 1, n)
        counts = jnp.zeros((batch,), jnp.int32)
        return AdaptiveState(
            t=t0,
            dt=dt,
            y=y0,
            f=f0 if self.settings.tableau.fsal else None,
            k=jnp.ones((batch,), jnp.int32),
            saves=(jnp.zeros(shape, self.ts.dtype), jnp.zeros(shape, self.ts.dtype)),
            control=ControllerState.start(batch, self.ts.dtype),
            accepted=counts,
            rejected=counts,
            failed=jnp.zeros((batch,), bool),
            nonfinite=jnp.zeros((batch,), bool),
            last_dt=dt,
        )

    def running(self, c: AdaptiveState):
        return (c.k < self.num_saves) & ~c.failed

    def attempt(self, c: AdaptiveState) -> Trial:
        """A step of every member, clipped onto its next save time (finished members take a
        harmless small step whose result is discarded)."""
        running = self.running(c)
        members = jnp.arange(c.k.shape[0])
        target = self.ts[members, jnp.minimum(c.k, self.num_saves - 1)]
        remaining = target - c.t
        clipped = c.dt >= remaining * (1 - 1e-12)
        h = jnp.where(clipped, remaining, c.dt)
        h = jnp.where(running, h, 1e-3 * jnp.abs(c.dt) + 1e-300)
        t1 = jnp.where(clipped, target, c.t + h)
        tableau = self.settings.tableau
        f_start = c.f if tableau.fsal else self.field(c.t, c.y)
        y1, error, f_last = rk_step(self.field, tableau, c.t, h, c.y, f_start)
        return Trial(running, clipped, h, t1, y1, error, f_last)

    def advance(
        self, c: AdaptiveState, trial: Trial, proposal: StepProposal, finite, tiny_step
    ) -> AdaptiveState:
        """The next carry: accepted members move to ``t1`` (projected onto the constraints),
        saving when they land on a save time; running members take the proposed step size."""
        running = trial.running
        accept = proposal.keep & running
        fail = running & ~proposal.keep & (trial.h <= tiny_step)
        y1 = self.field.project(trial.t1, trial.y1)
        save = accept & trial.clipped
        return AdaptiveState(
            t=jnp.where(accept, trial.t1, c.t),
            dt=jnp.where(running, proposal.dt, c.dt),
            y=select(accept, y1, c.y),
            f=select(accept, trial.f_last, c.f) if self.settings.tableau.fsal else None,
            k=c.k + save.astype(jnp.int32),
            saves=_write_saves(c.saves, c.k, save, y1, self.num_saves),
            control=c.control.after(proposal, accept, running),
            accepted=c.accepted + accept.astype(jnp.int32),
            rejected=c.rejected + (running & ~proposal.keep).astype(jnp.int32),
            failed=c.failed | fail,
            nonfinite=c.nonfinite | (fail & ~finite),
            last_dt=jnp.where(running, jax.lax.stop_gradient(trial.h), c.last_dt),
        )

    def body(self, c: AdaptiveState, tiny_step) -> AdaptiveState:
        trial = self.attempt(c)
        err, finite = error_norm(self.settings, trial.error, c.y, trial.y1)
        proposal = propose_step(self.settings, err, trial.h, c.dt, trial.clipped, c.control)
        return self.advance(c, trial, proposal, finite, tiny_step)

    def finish(self, final: AdaptiveState):
        """``(saved (q, q̇) each (T−1, B, n), stats, record)`` of the final carry."""
        num_saves = self.num_saves
        saved = tuple(jnp.moveaxis(s[:, 1:num_saves], 1, 0) for s in final.saves)
        stats = {
            "num_steps": final.accepted + final.rejected,
            "num_accepted_steps": final.accepted,
            "num_rejected_steps": final.rejected,
        }
        code = jnp.where(
            final.failed,
            jnp.where(final.nonfinite, FailureCode.NONFINITE, FailureCode.STEP_SIZE_COLLAPSED),
            jnp.where(final.k >= num_saves, FailureCode.COMPLETED, FailureCode.MAX_STEPS),
        )
        record = LoopRecord(code.astype(jnp.int32), final.k - 1, final.t, final.last_dt, *final.y)
        return saved, stats, jax.lax.stop_gradient(record)

    def run(self, y0: State, dt0):
        """The loop from ``y0`` (``dt0``: the first step, ``None``: Hairer's choice)."""
        tiny_step = self.tiny_step()

        def cond(c: AdaptiveState):
            return jnp.any(self.running(c))

        def body(c: AdaptiveState) -> AdaptiveState:
            return self.body(c, tiny_step)

        init = self.init(y0, dt0)
        max_steps = self.settings.max_steps
        if self.settings.loop_kind == "checkpointed":
            # The saves are write-only buffers: the checkpoints hold the small loop state only.
            final = eqxi.while_loop(
                cond, body, init, max_steps=max_steps, buffers=lambda c: c.saves, kind="checkpointed"
            )
        else:
            final = eqxi.while_loop(cond, body, init, max_steps=max_steps, kind="lax")
        return self.finish(final)
