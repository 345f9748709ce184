"""A solver whose step is traced once per solve, however often diffrax traces its loop body.

``diffrax.diffeqsolve`` traces the body of its solver loop three times: twice under
``eqx.filter_eval_shape`` (to find which parts of its state stay static, a second time when the
first finds some traced) and once for the loop itself. Each trace runs the solver's step in
Python, and with it the equations of motion (a KKT solve) at every Runge–Kutta stage and the
projection. `StepOnce` wraps the solver so that its ``step`` is an ``equinox.filter_jit``
function: the first trace records it, the other two are served from JAX's tracing cache (same
function, same static parts, same abstract arguments). The program is unchanged (XLA inlines
the call); only tracing time is saved.
"""

import diffrax
import equinox as eqx

from .forwarding import ForwardingSolver


@eqx.filter_jit
def _step(solver, terms, t0, t1, y0, args, solver_state, made_jump):
    return solver.step(terms, t0, t1, y0, args, solver_state, made_jump)


class StepOnce(ForwardingSolver, diffrax.AbstractWrappedSolver):
    """``solver`` with its ``step`` traced once per solve (see module). ``isinstance`` checks
    see the wrapped solver (diffrax's wrapped-solver convention)."""

    solver: diffrax.AbstractSolver  # pyright: ignore[reportIncompatibleVariableOverride]

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        return _step(self.solver, terms, t0, t1, y0, args, solver_state, made_jump)
