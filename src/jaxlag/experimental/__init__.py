"""Experimental pieces of jaxlag, with no stability promise (as ``equinox.internal``).

The ensemble integrator's GPU kernel, written with ``jax.experimental.pallas``: the per-member
equations of motion evaluated lane-wise (every array entry one column of the batch) inside a
Pallas kernel. ``jl.simulate_batch`` uses it for ``jl.Ensemble(backend="pallas")``; it runs on CPU
in Pallas's interpreter (``backend="pallas-interpret"``), which is how the tests check it.
"""

from .._batch.lanes import lanewise as lanewise
from .._batch.pallas import integrate_pallas as integrate_pallas
