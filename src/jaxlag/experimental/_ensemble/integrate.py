r"""One loop for a whole ensemble: batched explicit Runge–Kutta with the batch as an array axis.

``simulate_batch(..., method=jl.Vmap())`` is ``jax.vmap`` of ``diffrax.diffeqsolve``: every member
runs diffrax's solver loop, and ``vmap`` turns the loop into a batched ``while_loop`` whose body
is the whole of diffrax's step machinery. On an accelerator each iteration launches dozens of small
kernels. Here the state of all ``B`` members is one array pair ``q, q̇`` of shape ``(B, n)``
advanced by **one** loop whose body is one explicit Runge–Kutta step of the batch:

    k_i = f(t + c_i h, y + h Σ_{j<i} a_ij k_j),   y₁ = y + h Σ b_i k_i,   e = h Σ b̂_i k_i

with ``f(t, (q, q̇)) = (q̇, q̈)`` the library's own equations of motion
([`EquationsOfMotion`][jaxlag.EquationsOfMotion]: ``M q̈ = F + Jᵀλ + Aᵀμ`` by the range-space KKT solve)
``jax.vmap``-ed over the batch axis inside the body, and ``(c, a, b, b̂)`` the Butcher tableau of
the diffrax solver passed as ``solver=`` (``diffrax.Tsit5().tableau``, ...; [`RK4`][jaxlag.RK4] is the
classic fourth-order method as a diffrax solver). Constrained systems are projected onto the
manifold after every accepted step with the same [`Projection`][jaxlag.Projection] as ``simulate``.

The pieces, one job each: `jaxlag.experimental._ensemble.settings` (the diffrax objects checked and
made static), `.step` (the batched field and one Runge–Kutta step), `.constant` (constant steps),
`.controller` (step-size control) and `.adaptive` (the adaptive loop), `.outcome` (how each
member ended: `member_failures` turns it into the `Failure` record of ``jl.simulate``, with the
unreached saves ``inf``); the GPU kernel backend is `jaxlag.experimental._ensemble.pallas`.
"""

import equinox as eqx
import jax.numpy as jnp

from ..._checks import initial_state_diagnostics, validate_initial_state
from ..._mechanics.constant_mass import with_constant_mass
from .adaptive import AdaptiveLoop
from .constant import constant_loop
from .settings import EnsembleSettings
from .step import BatchedField

__all__ = ["ensemble_problem", "integrate_ensemble", "as_member_times"]


def ensemble_problem(system, q0, qd0, ts, member_args, shared_args, baumgarte, projection, check, tolerance):
    """Checked initial states and the `BatchedField` of a batch (inside ``jit``):
    ``(field, (q0, q̇0), diagnostics)``. ``check``: ``True`` compiles the initial-state check in
    (static message), ``"host"`` returns every member's diagnostics for the host to raise with
    the numbers and the member (`raise_for_initial_states`; else
    ``diagnostics`` is ``None``), ``False`` skips it."""

    def prepare(q, qd, t, member):
        args = eqx.combine(member, shared_args)
        system.check(q, qd, t, args)
        diagnostics = None
        if check == "host":
            diagnostics = initial_state_diagnostics(system, q, qd, t, args, tolerance)
        elif check:
            q, qd = validate_initial_state(system, q, qd, t, args, tolerance)
        fast = with_constant_mass(system, q, qd, t, args)
        return q, qd, fast.constant_mass, diagnostics

    q0, qd0, constant_mass, diagnostics = eqx.filter_vmap(prepare)(q0, qd0, ts[:, 0], member_args)
    field = BatchedField(system, baumgarte, projection, member_args, shared_args, constant_mass)
    return field, (q0, qd0), diagnostics


def integrate_ensemble(field: BatchedField, settings: EnsembleSettings, ts, y0, dt0, grid=None):
    """Run the loop; returns ``(saved (q, q̇) each (T−1, B, n), stats, record)``: ``record``
    the adaptive loop's `LoopRecord`, ``None`` for constant steps (every member runs to
    its end; `member_failures` finds the non-finite ones).

    ``ts`` (B, T), the first column being the start times; ``grid = (m, inner, uniform)`` for
    constant steps: ``m`` (B, T−1) steps per save interval (see `constant_grid`), ``inner``
    its maximum (static) and ``uniform`` whether every entry equals it (static).
    """
    if settings.adaptive:
        return AdaptiveLoop(field, settings, ts).run(y0, dt0)
    if grid is None:
        raise ValueError("integrate_ensemble needs grid=(m, inner, uniform) for constant steps.")
    steps_per_interval, inner, uniform = grid[:3]
    saved, stats, _ = constant_loop(field, settings, ts, y0, steps_per_interval, inner, uniform)
    return saved, stats, None


def as_member_times(ts, batch, dtype):
    """``ts`` as (B, T): shared (T,) rows broadcast, or per member (B, T)."""
    ts = jnp.asarray(ts, dtype=dtype)
    if ts.ndim == 1:
        ts = jnp.broadcast_to(ts, (batch, ts.shape[0]))
    if ts.ndim != 2 or ts.shape[0] != batch or ts.shape[1] < 2:
        raise ValueError(
            f"ts must have shape (T,) or (B, T) with T ≥ 2 for the ensemble integrator (B = {batch}); "
            f"got {ts.shape}."
        )
    return ts
