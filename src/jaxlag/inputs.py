r"""Time-table inputs: ``u(t)`` from samples ``(tᵢ, uᵢ)``, for forces, torques and drives.

Three interpolations of one table ``ts = (t₀ < t₁ < … < t_{N−1})``, ``values`` of shape
``(N,)`` or ``(N, *shape)``:

- `ZeroOrderHold`: ``u(t) = uᵢ`` for ``tᵢ ≤ t < tᵢ₊₁`` (piecewise constant, right-continuous:
  at a sample time the new value already holds). Jumps at ``t₁, …, t_{N−1}``.
- `PiecewiseLinear`: straight lines between the samples. Continuous, kinks at the samples.
- `CubicSpline`: the natural cubic spline through the samples (``u″ = 0`` at both ends).
  Twice continuously differentiable; ``u‴`` jumps at the samples.

Outside ``[t₀, t_{N−1}]`` every table holds its end value (``u(t) = u₀`` before ``t₀`` and
``u_{N−1}`` after ``t_{N−1}``), so a simulation may run past the last sample.

A table is an equinox Module (a pytree with the arrays ``ts`` and ``values`` as leaves): put it
in ``args`` and read it in a force function,

    system = jl.System(L, forces=lambda q, qd, t, args: jnp.array([args["u"](t)]))
    traj = jl.simulate(system, q0, qd0, ts, args={"u": inputs.ZeroOrderHold(t_samples, u_samples)})

It works under ``jax.jit``, ``jax.vmap`` (build the table inside the mapped function, or build a
batch with ``jax.vmap(lambda v: ZeroOrderHold(ts, v))(values)`` for ``jl.simulate_batch(...,
args_axes=0)``) and ``jax.grad`` with respect to ``values`` (trajectory optimization).

**Breakpoints.** The equations of motion are not smooth at the samples (a hold jumps, a linear
table has kinks), and an adaptive step-size controller that does not know where they are either
wastes rejected steps there or, with a short pulse, steps over it. [`simulate`][jaxlag.simulate] finds
every table in ``args`` and makes the solver step exactly onto its breakpoints: the jumps of a
`ZeroOrderHold` become diffrax ``jump_ts`` (the step ends just before the jump and the next
one starts just after it, re-evaluating the vector field), the samples of the other tables
``step_ts``. This is done for the default controller and for any adaptive controller you give (a
``diffrax.PIDController``, or a ``diffrax.ClipStepSizeController`` whose own ``step_ts`` and
``jump_ts`` are kept). A fixed step (``diffrax.ConstantStepSize``, ``diffrax.StepTo``) is left as it
is: choose steps that land on the samples. For a table that ``args`` does not hold (one captured
by a closure), pass ``stepsize_controller=inputs.with_breakpoints(controller, table)``.
"""

from ._inputs import (
    AbstractTimeTable as AbstractTimeTable,
)
from ._inputs import (
    CubicSpline as CubicSpline,
)
from ._inputs import (
    PiecewiseLinear as PiecewiseLinear,
)
from ._inputs import (
    ZeroOrderHold as ZeroOrderHold,
)
from ._inputs import (
    with_breakpoints as with_breakpoints,
)

__all__ = [
    "AbstractTimeTable",
    "CubicSpline",
    "PiecewiseLinear",
    "ZeroOrderHold",
    "with_breakpoints",
]
