"""The fit's small programs, compiled for the time to the first result.

`jl.fit` drives its optimizer from the host: besides the program of the residuals and their
Jacobian it compiles a few small ones (the optimizer's state, its step, the statistics at the
optimum) that run in microseconds on arrays of the residuals' size. On the CPU most of their
compile time is LLVM optimizing code whose run time does not matter: `lean_jit` compiles them
with LLVM's optimizations off (XLA's ``xla_backend_optimization_level=0``), on top of jaxlag's
CPU options (`jaxlag._compile.compiler_options`). Measured on the README demo's fit (2-core
CPU, one pinned core, CPU seconds): the Levenberg–Marquardt step 0.49 → 0.14 s of XLA time.
Off the CPU, inside a transformation, or with an XLA that refuses the option, they compile as
every other jaxlag program (`jaxlag._compile.filter_jit`).
"""

import functools
from typing import Any

import equinox as eqx
import jax

from .. import _compile as compilation
from .._errors import current_on_failure, on_failure

#: XLA options added on the CPU for the fit's small programs: LLVM's optimizations off.
LEAN_CPU_OPTIONS = {"xla_backend_optimization_level": 0}

_refused: list[bool] = []  # the option was refused once: compile with jaxlag's options from then on


class _LeanJit:
    """``filter_jit(fn)`` compiled with `LEAN_CPU_OPTIONS` when it is its own program on the CPU."""

    def __init__(self, fn):
        functools.update_wrapper(self, fn)
        self._fn = fn
        self._plain = compilation.filter_jit(fn)
        self._lean: dict[tuple, Any] = {}

    def _wrapper(self) -> Any:
        options = compilation.compiler_options()
        if _refused or not options or not compilation.no_transformation_active():
            return None
        choice = current_on_failure()
        key = (tuple(sorted(options.items())), choice)
        wrapper = self._lean.get(key)
        if wrapper is None:
            fn = self._fn

            @functools.wraps(fn)
            def traced(*args, **kwargs):
                with on_failure(choice):
                    return fn(*args, **kwargs)

            jitkwargs: dict[str, Any] = {"compiler_options": {**options, **LEAN_CPU_OPTIONS}}
            wrapper = eqx.filter_jit(traced, **jitkwargs)
            self._lean[key] = wrapper
        return wrapper

    def __call__(self, *args, **kwargs):
        wrapper = self._wrapper()
        if wrapper is not None:
            try:
                return wrapper(*args, **kwargs)
            except jax.errors.JaxRuntimeError as error:
                if "xla_backend_optimization_level" not in str(error):
                    raise
                _refused.append(True)
        return self._plain(*args, **kwargs)


def lean_jit(fn) -> Any:
    """`jaxlag._compile.filter_jit` for a program whose run time is negligible next to its
    compile time: on the CPU, at the top level, compiled without LLVM's optimizations."""
    return _LeanJit(fn)
