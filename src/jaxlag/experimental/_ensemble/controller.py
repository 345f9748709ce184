r"""Step-size control of the adaptive loop, per member: diffrax's ``PIDController`` on arrays.

The error of a step is ``ε = ‖e / (atol + rtol max(|y|, |y₁|))‖_RMS`` over the ``2n`` state
entries, accepted when ``ε < 1``; the next step is
``h · clip(safety · ε₁^{-β₁} ε₀^{-β₂} ε₋₁^{-β₃}, factormin, factormax)`` with
``β = (pcoeff + icoeff + dcoeff, −(pcoeff + 2 dcoeff), dcoeff) / p`` and ``p`` the solver's error
order (after a step clipped onto a save time the unclipped proposal is kept). None of it is
differentiated (as in diffrax): no zero-times-infinite cotangents from the norm of a vanishing error.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .settings import EnsembleSettings

__all__ = ["rms", "initial_step", "bounded", "error_norm", "ControllerState", "StepProposal", "propose_step"]


def rms(tree, size):
    """The root mean square over the last axis of every leaf, ``size`` entries in all."""
    return jnp.sqrt(sum(jnp.sum(x * x, axis=-1) for x in jax.tree.leaves(tree)) / size)


def _tolerances(settings: EnsembleSettings):
    """``(rtol, atol)``: always given with a ``PIDController``."""
    rtol, atol = settings.rtol, settings.atol
    assert rtol is not None and atol is not None, "adaptive settings carry rtol and atol"
    return rtol, atol


def initial_step(field, settings: EnsembleSettings, t0, y0, f0):
    """Hairer's starting step, as diffrax's ``PIDController`` chooses it, per member."""
    size = 2 * y0[0].shape[1]
    t0, y0, f0 = jax.lax.stop_gradient((t0, y0, f0))
    rtol, atol = _tolerances(settings)
    scale = jax.tree.map(lambda y: atol + jnp.abs(y) * rtol, y0)
    d0 = rms(jax.tree.map(jnp.divide, y0, scale), size)
    d1 = rms(jax.tree.map(jnp.divide, f0, scale), size)
    small = (d0 < 1e-5) | (d1 < 1e-5)
    h0 = jnp.where(small, 1e-6, 0.01 * d0 / jnp.where(small, 1.0, d1))
    y1 = jax.tree.map(lambda y, f: y + h0[:, None] * f, y0, f0)
    f1 = field(t0 + h0, y1)
    d2 = rms(jax.tree.map(lambda a, b, s: (a - b) / s, f1, f0, scale), size) / h0
    max_d = jnp.maximum(d1, d2)
    h1 = jnp.where(
        max_d <= 1e-15,
        jnp.maximum(1e-6, h0 * 1e-3),
        (0.01 / jnp.where(max_d <= 1e-15, 1.0, max_d)) ** (1 / settings.error_order),
    )
    return jax.lax.stop_gradient(jnp.minimum(100 * h0, h1))


def bounded(settings: EnsembleSettings, dt):
    """``dt`` clipped to ``[dtmin, dtmax]`` (either bound may be absent)."""
    if settings.dtmax is not None:
        dt = jnp.minimum(dt, settings.dtmax)
    if settings.dtmin is not None:
        dt = jnp.maximum(dt, settings.dtmin)
    return dt


def error_norm(settings: EnsembleSettings, error, y, y1):
    """``(ε, finite)``: the scaled RMS error of each member's step, ``inf`` where the trial
    state ``y₁`` (or ``ε``) is not finite, and whether the trial state is finite."""
    rtol, atol = _tolerances(settings)
    scaled = jax.tree.map(
        lambda e, a, b: e / (atol + jnp.maximum(jnp.abs(a), jnp.abs(b)) * rtol),
        *jax.lax.stop_gradient((error, y, y1)),
    )
    err = rms(scaled, 2 * y[0].shape[1])
    finite = jnp.all(jnp.isfinite(y1[0]), axis=1) & jnp.all(jnp.isfinite(y1[1]), axis=1)
    return jnp.where(finite & jnp.isfinite(err), err, jnp.inf), finite


class ControllerState(eqx.Module):
    """The controller's memory, per member: ``1/ε`` of the last accepted step and of the one
    before (``inv``, ``inv_prev``), and whether the step to try next is at ``dtmin``."""

    inv: Float[Array, " batch"]
    inv_prev: Float[Array, " batch"]
    at_dtmin: Bool[Array, " batch"]

    @classmethod
    def start(cls, batch: int, dtype) -> "ControllerState":
        ones = jnp.ones((batch,), dtype)
        return cls(ones, ones, jnp.zeros((batch,), bool))

    def after(self, proposal: "StepProposal", accept, running) -> "ControllerState":
        """The memory after a step: ``accept``-ed members remember its error."""
        return ControllerState(
            inv=jnp.where(accept, proposal.inv, self.inv),
            inv_prev=jnp.where(accept, self.inv, self.inv_prev),
            at_dtmin=jnp.where(running, proposal.at_dtmin, self.at_dtmin),
        )


class StepProposal(eqx.Module):
    """The controller's verdict on a step, per member: whether to keep it, the next step to
    try, whether that is at ``dtmin``, and ``1/ε`` of this step (``1`` where ``ε`` is 0 or ∞)."""

    keep: Bool[Array, " batch"]
    dt: Float[Array, " batch"]
    at_dtmin: Bool[Array, " batch"]
    inv: Float[Array, " batch"]


def _factor(settings: EnsembleSettings, inv, memory: ControllerState, keep):
    """``clip(safety · ε₁^{-β₁} ε₀^{-β₂} ε₋₁^{-β₃})``: kept steps never shrink, rejected never grow."""
    p = settings.error_order
    beta1 = (settings.pcoeff + settings.icoeff + settings.dcoeff) / p
    beta2 = -(settings.pcoeff + 2 * settings.dcoeff) / p
    beta3 = settings.dcoeff / p
    factor = settings.safety * inv**beta1
    if beta2 != 0:
        factor = factor * memory.inv**beta2
    if beta3 != 0:
        factor = factor * memory.inv_prev**beta3
    factor = jnp.clip(
        factor,
        jnp.where(keep, 1.0, settings.factormin),
        jnp.where(keep, settings.factormax, settings.safety),
    )
    return jax.lax.stop_gradient(factor)


def propose_step(settings: EnsembleSettings, err, h, dt, clipped, memory: ControllerState) -> StepProposal:
    """The verdict on a step of size ``h`` with error ``err``: ``dt`` is the step proposed
    before ``h`` was ``clipped`` onto a save time; a step tried at ``dtmin`` is kept whatever its
    error (diffrax's ``force_dtmin``)."""
    keep = err < 1
    if settings.dtmin is not None:
        keep = keep | memory.at_dtmin
    inv = jax.lax.stop_gradient(1 / err)
    dt_next = h * _factor(settings, inv, memory, keep)
    dt_next = jnp.where(keep & clipped, jnp.maximum(dt_next, dt), dt_next)
    if settings.dtmax is not None:
        dt_next = jnp.minimum(dt_next, settings.dtmax)
    at_dtmin = memory.at_dtmin
    if settings.dtmin is not None:
        at_dtmin = dt_next <= settings.dtmin
        dt_next = jnp.maximum(dt_next, settings.dtmin)
    inv = jnp.where((inv == 0) | jnp.isinf(inv), 1.0, inv)
    return StepProposal(keep, dt_next, at_dtmin, inv)
