"""How jaxlag compiles its own programs: XLA options chosen for the time to the first result.

Research scripts run once, so compilation is part of the cost of every result. On the CPU,
XLA's newer MLIR fusion emitters compile each fused kernel as its own LLVM module; a diffrax
solve has ~90 of them, and compiling them dominates the first call. The older emitters
(``xla_cpu_use_fusion_emitters=False``) produce code that runs as fast on these small,
latency-bound programs. Measured on this project's 2-core CPU machine (``benchmarks/RESULTS.md``):

* README first example (particle on a sphere, 201 saves), XLA compile of the solve
  1.6-1.9 s → 0.9-1.0 s; its first ``jax.grad`` (forward sensitivities) 4.9 s → 1.8 s of XLA time;
* run time per step within ±5 % (double pendulum 1.03×, 10-link angle chain 0.96×, 10-link
  Cartesian chain 1.00×, same process, alternating, medians).

Programs that run once or a few times on small arrays (`jl.fit`'s optimizer step and statistics,
a linearization) are compiled by `lean_jit` instead: on the CPU, when called eagerly, also
without LLVM's optimizations, since there their compile time is all that counts.

Every program jaxlag compiles itself (``simulate``, ``simulate_batch``, ``fit``, the checks, the
derived quantities of a trajectory, ...) is jitted by `filter_jit`, which passes
`compiler_options` to ``jax.jit`` when the default backend is the CPU (on GPUs and TPUs
nothing changes). Inside a user's own ``jax.jit`` the outer program's options apply: pass
``compiler_options=jl.compiler_options()`` to it to get the same compile time. Set the
environment variable ``JAXLAG_COMPILER_OPTIONS=0`` to compile with XLA's defaults (as happens
by itself with an XLA that does not know the option: checked once, by one tiny compile).
"""

import functools
import os
from collections.abc import Callable
from typing import Any, overload

import equinox as eqx
import jax
import jax.extend.core as jcore
import numpy as np

from ._errors import current_on_failure, on_failure

#: XLA options for the CPU backend (see the module docstring for the measurements).
CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

#: ... and for a process that may run on one core only: XLA splits the LLVM module of a program
#: into parts compiled by parallel threads, which on one core only adds the cost of the parts.
SINGLE_CORE_OPTIONS = {"xla_cpu_parallel_codegen_split_count": 1}


def _one_core() -> bool:
    """Whether this process may run on a single core (its CPU affinity: a pinned process, a
    one-CPU container or batch job); False where the platform does not say."""
    try:
        return len(os.sched_getaffinity(0)) == 1
    except (AttributeError, OSError):
        return False


def _switched_off(variable: str) -> bool:
    """Whether the environment variable says 0/false/no/off (jaxlag's opt-outs)."""
    return os.environ.get(variable, "1").strip().lower() in ("0", "false", "no", "off")


def compiler_options(backend: str | None = None) -> dict:
    """The XLA options jaxlag compiles with on ``backend`` (default: JAX's default backend).

    Pass them to your own ``jax.jit(f, compiler_options=jl.compiler_options())`` around code
    that calls jaxlag: a jaxlag function traced inside your ``jit`` is compiled as part of your
    program, with its options. Empty on GPU/TPU, or when ``JAXLAG_COMPILER_OPTIONS=0``.
    """
    backend = jax.default_backend() if backend is None else backend
    if backend != "cpu" or _switched_off("JAXLAG_COMPILER_OPTIONS") or not _cpu_options_supported():
        return {}
    return {**CPU_COMPILER_OPTIONS, **(SINGLE_CORE_OPTIONS if _one_core() else {})}


@functools.cache
def _cpu_options_supported() -> bool:
    """Whether this XLA knows the options (older jaxlibs reject unknown ones): one tiny compile,
    once per process."""
    try:
        on_cpu = jax.device_put(np.float32(0), jax.devices("cpu")[0])
        options = {**CPU_COMPILER_OPTIONS, **SINGLE_CORE_OPTIONS}
        jax.jit(lambda x: x + 1, compiler_options=options).lower(on_cpu).compile()
        return True
    except Exception:  # noqa: BLE001 - any refusal: compile with XLA's defaults
        return False


#: Traces under which a jitted call is still compiled as a top-level program (evaluated eagerly,
#: possibly pushed forward or batched); under any other (``jit``, ``make_jaxpr``, ``eval_shape``,
#: reverse-mode linearization) it is staged into an enclosing program, where JAX forbids options.
_TOP_LEVEL_TRACES = ("EvalTrace", "JVPTrace", "BatchTrace")


def _trace_kinds() -> list[str] | None:
    """The class names of the active traces, innermost first, by ``jax.extend.core``'s current
    trace and each trace's ``parent_trace``; None when unknown (then callers are conservative)."""
    try:
        with jcore.take_current_trace() as trace:
            kinds = []
            while trace is not None and len(kinds) < 64:
                kinds.append(type(trace).__name__)
                trace = getattr(trace, "parent_trace", None)
            return kinds
    except Exception:  # noqa: BLE001 - JAX changed: be conservative
        return None


def _compiled_at_top_level() -> bool:
    """Whether a ``jax.jit`` called now becomes its own compiled program (conservative: False
    when unsure; then the program is compiled with XLA's defaults, never a different result)."""
    kinds = _trace_kinds()
    return kinds is not None and all(kind in _TOP_LEVEL_TRACES for kind in kinds)


def no_transformation_active() -> bool:
    """Whether code runs outside every JAX transformation (no ``jit``, ``grad``, ``vmap``
    trace): then no function can close over a traced value. Conservative: False when unsure."""
    kinds = _trace_kinds()
    return kinds is not None and all(kind == "EvalTrace" for kind in kinds)


def _traced_under(fn, choice):
    """``fn``, traced with the compiled checks' ``choice`` in force (`jaxlag._errors.on_failure`)."""

    @functools.wraps(fn)
    def traced(*args, **kwargs):
        with on_failure(choice):
            return fn(*args, **kwargs)

    return traced


class _BackendJit:
    """``eqx.filter_jit(fn)`` that compiles with `compiler_options` of the default backend.

    Two wrappers are kept (tuned and plain); which one runs is chosen at each call: tuned when
    the call compiles its own program on the CPU, plain when it is traced into an enclosing
    ``jit`` (JAX accepts options only on top-level programs). The tuned one calls the plain one,
    so the function is traced once for both: a trace nested in ``jax.eval_shape`` or
    ``jax.make_jaxpr`` (which takes the plain one) serves the top-level call. Both are created
    lazily, one pair per choice of the compiled checks in force (`jaxlag._errors.on_failure`),
    which the function is traced under.
    """

    def __init__(self, fn, jitkwargs, cpu_options=True):
        functools.update_wrapper(self, fn)
        self._fn = fn
        self._jitkwargs = jitkwargs
        self._cpu_options = cpu_options
        self._wrappers: dict[tuple[Any, Any], Any] = {}  # (options or False, checks' choice)

    def _wrapper(self) -> Any:
        options = compiler_options() if self._cpu_options and _compiled_at_top_level() else {}
        # The compiled checks' choice in force (jaxlag._errors.on_failure) is part of the key:
        # a program traced under NaNOnFailure never serves a call under RaiseOnFailure.
        choice = current_on_failure()
        if not options:
            return self._plain(choice)
        key = (tuple(sorted(options.items())), choice)
        wrapper = self._wrappers.get(key)
        if wrapper is None:
            # The tuned program is a call of the plain one, whose trace JAX caches (per jit and
            # options): a trace of the plain one nested in another (``jax.eval_shape`` of the
            # output shapes, a ``make_jaxpr``) serves the top-level call, and the reverse. XLA
            # inlines the call: the compiled program is the same.
            plain = self._plain(choice)
            kwargs = dict(self._jitkwargs)
            kwargs["compiler_options"] = {**options, **kwargs.get("compiler_options", {})}
            wrapper = eqx.filter_jit(functools.wraps(self._fn)(lambda *a, **k: plain(*a, **k)), **kwargs)
            self._wrappers[key] = wrapper
        return wrapper

    def _plain(self, choice) -> Any:
        """The wrapper without options, tracing the function under ``choice``."""
        wrapper = self._wrappers.get((False, choice))  # no options
        if wrapper is None:
            traced = _traced_under(self._fn, choice)
            wrapper = self._wrappers[(False, choice)] = eqx.filter_jit(traced, **self._jitkwargs)
        return wrapper

    def __call__(self, *args, **kwargs):
        return self._wrapper()(*args, **kwargs)

    def lower(self, *args, **kwargs):
        return self._wrapper().lower(*args, **kwargs)


@overload
def filter_jit(
    fn: None = None, *, cpu_options: bool = True, **jitkwargs: Any
) -> Callable[[Callable], _BackendJit]: ...
@overload
def filter_jit(fn: Callable, *, cpu_options: bool = True, **jitkwargs: Any) -> _BackendJit: ...
def filter_jit(fn: Callable | None = None, *, cpu_options: bool = True, **jitkwargs: Any) -> Any:
    """``equinox.filter_jit`` compiling with `compiler_options` (usable as a decorator).

    ``cpu_options=False``: XLA's defaults, for programs dominated by dense network layers (the
    learned models' losses and steps): there XLA's fusion emitters run them up to 1.5× faster
    (a DeLaN's forward pass, measured), which outweighs their longer compile over a training run.
    The program is still traced under the compiled checks' choice in force."""
    if fn is None:
        return functools.partial(filter_jit, cpu_options=cpu_options, **jitkwargs)
    return _BackendJit(fn, jitkwargs, cpu_options)


@overload
def jit(fn: None = None, **jitkwargs: Any) -> Callable[[Callable], jax.stages.Wrapped]: ...
@overload
def jit(fn: Callable, **jitkwargs: Any) -> jax.stages.Wrapped: ...
def jit(fn: Callable | None = None, **jitkwargs: Any) -> Any:
    """``jax.jit`` compiling with `compiler_options` when it is a top-level program."""
    if fn is None:
        return functools.partial(jit, **jitkwargs)
    options = compiler_options() if _compiled_at_top_level() else {}
    if options:
        jitkwargs["compiler_options"] = {**options, **jitkwargs.get("compiler_options", {})}
    return jax.jit(fn, **jitkwargs)


#: XLA options added on the CPU for programs whose run time is negligible next to their compile
#: time (`lean_jit`): LLVM's optimizations off.
LEAN_CPU_OPTIONS = {"xla_backend_optimization_level": 0}

_refused: list[bool] = []  # the option was refused once: compile with jaxlag's options from then on


class _LeanJit:
    """``filter_jit(fn)`` compiled with `LEAN_CPU_OPTIONS` when it is its own program on the CPU."""

    def __init__(self, fn):
        functools.update_wrapper(self, fn)
        self._fn = fn
        self._plain = filter_jit(fn)
        self._lean: dict[tuple, Any] = {}

    def _wrapper(self) -> Any:
        options = compiler_options()
        if _refused or not options or not no_transformation_active():
            return None
        choice = current_on_failure()
        key = (tuple(sorted(options.items())), choice)
        wrapper = self._lean.get(key)
        if wrapper is None:
            jitkwargs: dict[str, Any] = {"compiler_options": {**options, **LEAN_CPU_OPTIONS}}
            wrapper = eqx.filter_jit(_traced_under(self._fn, choice), **jitkwargs)
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
    """`filter_jit` for a program whose run time is negligible next to its compile time (run once
    or a few times on small arrays: `jl.fit`'s optimizer step and statistics, a linearization):
    on the CPU, when called outside every transformation, compiled without LLVM's optimizations
    (XLA's ``xla_backend_optimization_level=0``) on top of `compiler_options`. Measured: the
    README demo's Levenberg–Marquardt step 0.49 → 0.14 s of XLA time; the bicycle's
    linearization 18.8 → 8.0 s, each later call 75 → 84 ms (host work dominates). Off the CPU,
    inside a transformation, or with an XLA that refuses the option, as `filter_jit`."""
    return _LeanJit(fn)
