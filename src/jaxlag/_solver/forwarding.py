"""``ForwardingSolver``: the base of jaxlag's diffrax solver wrappers.

A wrapper changes one thing about the solver it holds (``step`` for
`ProjectedSolver` and `StepOnce`, the state
for `TangentSolver`) and forwards the rest of diffrax's solver
interface to it: term structure, interpolation, orders, ``init``, ``step``, ``func`` and the
Runge–Kutta ``scan_kind`` (which diffrax's adjoints set on the solver they are handed; the
property returns the wrapped solver's field, so their ``eqx.tree_at`` reaches it). Whether
``isinstance`` sees through the wrapper is the subclass's choice (diffrax's
``AbstractWrappedSolver``).
"""

import diffrax
from equinox import AbstractVar


class ForwardingSolver(diffrax.AbstractSolver):
    """Forwards diffrax's solver interface to ``self.solver`` (see module)."""

    # The properties below stand for diffrax's abstract fields and class variables, which equinox
    # accepts and pyright cannot see: hence the line-level ignores.

    solver: AbstractVar[diffrax.AbstractSolver]

    @property
    def scan_kind(self):
        return getattr(self.solver, "scan_kind", None)

    @property
    def term_structure(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.solver.term_structure

    @property
    def interpolation_cls(self):  # pyright: ignore[reportIncompatibleMethodOverride]
        return self.solver.interpolation_cls

    @property
    def term_compatible_contr_kwargs(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.solver.term_compatible_contr_kwargs

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        return self.solver.step(terms, t0, t1, y0, args, solver_state, made_jump)

    def func(self, terms, t0, y0, args):
        return self.solver.func(terms, t0, y0, args)


class ForwardingAdaptiveController(diffrax.AbstractAdaptiveStepSizeController):
    """Base of jaxlag's adaptive step-size controller wrappers: the tolerances and norm are the
    wrapped ``self.controller``'s (diffrax reads them, e.g. for implicit solvers)."""

    # pyright takes diffrax's abstract rtol/atol/norm for fields of the synthesized __init__ (they
    # are properties here): subclasses are constructed from their controller alone, under ignores.

    controller: AbstractVar[diffrax.AbstractAdaptiveStepSizeController]

    @property
    def rtol(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.controller.rtol

    @property
    def atol(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.controller.atol

    @property
    def norm(self):  # pyright: ignore[reportIncompatibleMethodOverride]
        return self.controller.norm
