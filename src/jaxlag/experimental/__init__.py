"""Experimental pieces of jaxlag, with no stability promise (as ``equinox.internal``).

The ensemble integrator: `simulate_ensemble` advances a whole batch as one explicit
Runge–Kutta loop (``jl.simulate_batch(..., method=jl.Ensemble())`` runs it), and its GPU kernel,
written with ``jax.experimental.pallas``: the per-member equations of motion evaluated
lane-wise (every array entry one column of the batch) inside a Pallas kernel
(``jl.Ensemble(backend="pallas")``); it runs on CPU in Pallas's interpreter
(``backend="pallas-interpret"``), which is how the tests check it.
"""

from ._ensemble.api import simulate_ensemble as simulate_ensemble
from ._ensemble.lanes import lanewise as lanewise
from ._ensemble.pallas import integrate_pallas as integrate_pallas
