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

Every program jaxlag compiles itself (``simulate``, ``simulate_batch``, ``fit``, the checks, the
derived quantities of a trajectory, ...) is jitted by :func:`filter_jit`, which passes
:func:`compiler_options` to ``jax.jit`` when the default backend is the CPU (on GPUs and TPUs
nothing changes). Inside a user's own ``jax.jit`` the outer program's options apply: pass
``compiler_options=jl.compiler_options()`` to it to get the same compile time. Set the
environment variable ``JAXLAG_COMPILER_OPTIONS=0`` to compile with XLA's defaults (as happens
by itself with an XLA that does not know the option: checked once, by one tiny compile).

**Persistent compilation cache.** Unless the user has configured JAX's cache (the
``JAX_COMPILATION_CACHE_DIR`` variable or ``jax_compilation_cache_dir``), importing jaxlag points
it at ``$XDG_CACHE_HOME/jaxlag/jax`` (default ``~/.cache/jaxlag/jax``) and caches programs of any
compile time (JAX's default threshold, 1 s, would skip every program jaxlag compiles now). A
second run of the same script then loads its programs instead of compiling them.
``JAXLAG_COMPILATION_CACHE=0`` turns this off (and jaxlag's saved programs,
:mod:`jaxlag.saved_programs`, which also spare a second run the tracing). JAX 0.10 does not store
programs with host callbacks, so jaxlag keeps them out of the programs it runs itself:
``simulate``'s solve and the forward sensitivities of ``jax.grad`` check the initial state on the
host (before the program), diffrax's own checks of times already checked on the host compile
without callbacks (:func:`diffrax_checks_done_on_host`), and ``jl.fit``'s least-squares program
and ``simulate_batch``'s program return their checks for the host to raise. (A ``jit`` of your own
is cached if it has no callbacks, e.g. ``jl.simulate(..., throw=False, check_initial_state=False,
check_times=False)``.)
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

#: XLA options for the CPU backend (see the module docstring for the measurements).
CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


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
    return dict(CPU_COMPILER_OPTIONS)


@functools.cache
def _cpu_options_supported() -> bool:
    """Whether this XLA knows the options (older jaxlibs reject unknown ones): one tiny compile,
    once per process."""
    try:
        on_cpu = jax.device_put(np.float32(0), jax.devices("cpu")[0])
        jax.jit(lambda x: x + 1, compiler_options=CPU_COMPILER_OPTIONS).lower(on_cpu).compile()
        return True
    except Exception:  # noqa: BLE001 - any refusal: compile with XLA's defaults
        return False


#: Traces under which a jitted call is still compiled as a top-level program (evaluated eagerly,
#: possibly pushed forward or batched); under any other (``jit``, ``make_jaxpr``, ``eval_shape``,
#: reverse-mode linearization) it is staged into an enclosing program, where JAX forbids options.
_TOP_LEVEL_TRACES = ("EvalTrace", "JVPTrace", "BatchTrace")


def _compiled_at_top_level() -> bool:
    """Whether a ``jax.jit`` called now becomes its own compiled program (conservative: False
    when unsure). Reads JAX's trace stack, which has no public API; any change there only loses
    the tuned options, never a result."""
    try:
        from jax._src import core

        stack = core.unsafe_get_trace_stack(core.trace_ctx.trace)
        return all(type(trace).__name__ in _TOP_LEVEL_TRACES for trace in stack)
    except Exception:  # noqa: BLE001 - private API moved: compile with XLA's defaults
        return False


def no_transformation_active() -> bool:
    """Whether code runs outside every JAX transformation (no ``jit``, ``grad``, ``vmap``
    trace): then no function can close over a traced value. Conservative: False when unsure
    (JAX's trace stack has no public API)."""
    try:
        from jax._src import core

        stack = core.unsafe_get_trace_stack(core.trace_ctx.trace)
        return all(type(trace).__name__ == "EvalTrace" for trace in stack)
    except Exception:  # noqa: BLE001 - private API moved: assume a transformation
        return False


class _BackendJit:
    """``eqx.filter_jit(fn)`` that compiles with :func:`compiler_options` of the default backend.

    Two wrappers are kept (tuned and plain); which one runs is chosen at each call: tuned when
    the call compiles its own program on the CPU, plain when it is traced into an enclosing
    ``jit`` (JAX accepts options only on top-level programs). Both are created lazily.
    """

    def __init__(self, fn, jitkwargs):
        functools.update_wrapper(self, fn)
        self._fn = fn
        self._jitkwargs = jitkwargs
        self._wrappers: dict[bool, object] = {}

    def _wrapper(self):
        options = compiler_options() if _compiled_at_top_level() else {}
        tuned = bool(options)
        wrapper = self._wrappers.get(tuned)
        if wrapper is None:
            kwargs = dict(self._jitkwargs)
            if tuned:
                kwargs["compiler_options"] = {**options, **kwargs.get("compiler_options", {})}
            wrapper = self._wrappers[tuned] = eqx.filter_jit(self._fn, **kwargs)
        return wrapper

    def __call__(self, *args, **kwargs):
        return self._wrapper()(*args, **kwargs)

    def lower(self, *args, **kwargs):
        return self._wrapper().lower(*args, **kwargs)


def filter_jit(fn=None, **jitkwargs):
    """``equinox.filter_jit`` compiling with :func:`compiler_options` (usable as a decorator)."""
    if fn is None:
        return functools.partial(filter_jit, **jitkwargs)
    return _BackendJit(fn, jitkwargs)


def jit(fn=None, **jitkwargs):
    """``jax.jit`` compiling with :func:`compiler_options` when it is a top-level program."""
    if fn is None:
        return functools.partial(jit, **jitkwargs)
    options = compiler_options() if _compiled_at_top_level() else {}
    if options:
        jitkwargs["compiler_options"] = {**options, **jitkwargs.get("compiler_options", {})}
    return jax.jit(fn, **jitkwargs)


def user_cache_path(name: str) -> str:
    """``$XDG_CACHE_HOME/jaxlag/<name>`` (default ``~/.cache/jaxlag/<name>``): where jaxlag's
    caches live (JAX's persistent cache, :mod:`jaxlag.saved_programs`)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "jaxlag", name)


def enable_persistent_cache() -> str | None:
    """Point JAX's persistent compilation cache at jaxlag's user cache directory (see the module
    docstring) unless the user configured one or set ``JAXLAG_COMPILATION_CACHE=0``. Returns the
    directory in use by this call, or None."""
    if _switched_off("JAXLAG_COMPILATION_CACHE"):
        return None
    if os.environ.get("JAX_COMPILATION_CACHE_DIR") or jax.config.jax_compilation_cache_dir:
        return None  # the user's own cache settings stand
    directory = user_cache_path("jax")
    try:
        os.makedirs(directory, exist_ok=True)
    except OSError:
        return None  # no writable cache directory: compile as usual
    jax.config.update("jax_compilation_cache_dir", directory)
    if jax.config.jax_persistent_cache_min_compile_time_secs == 1.0:  # JAX's default
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return directory


# ----------------------------------------------------------------------------- checked on the host
_PROLOGUE_LOCK = threading.RLock()
_prologue_saved: list = []  # equinox's functions to restore, innermost last


@contextlib.contextmanager
def diffrax_checks_done_on_host(enabled: bool = True):
    """While tracing the start of a ``diffrax.diffeqsolve`` whose inputs jaxlag has already
    checked on the host, compile diffrax's own input checks without host callbacks.

    diffrax guards its inputs with ``eqx.error_if`` (``(t1 − t0)·dt0 ≥ 0``; save times ordered
    and inside ``[t0, t1]``). With traced times each check is a host callback in the program,
    and JAX 0.10 does not store programs with host callbacks in its persistent cache: the
    solver, the most expensive program of a script, would be compiled again by every run.
    When the values were concrete, :func:`jaxlag.simulate` has checked them on the host, so the
    compiled checks are redundant: inside this context ``eqx.error_if`` calls that ask for the
    default behaviour get ``on_error="nan"`` instead (the same predicate, a NaN substitution,
    no callback). The explicit argument, not equinox's global ``EQX_ON_ERROR``, matters:
    equinox caches the traced check by its arguments, so a NaN variant never serves a later
    call outside the window.

    The switch replaces equinox's module-level ``branched_error_if`` (which ``eqx.error_if``
    calls), so it is held for the shortest window that covers those checks (suspended while
    diffrax traces the vector field for its shape check, :func:`outside_diffrax_prologue`): it
    ends at
    :func:`end_diffrax_prologue`, which jaxlag's step-size guard calls first thing in its
    ``init`` (diffrax initializes the controller right after checking its inputs; the solver
    loop is traced after that, with equinox restored), or at the end of the context. A user's
    own ``EQX_ON_ERROR`` other than ``raise`` is left alone, and if equinox's private layout has
    changed this does nothing (the program is then compiled with the callbacks, as before, and
    just not cached).
    """
    module = _equinox_errors()
    if not enabled or module is None or module.EQX_ON_ERROR != "raise":
        yield
        return
    with _PROLOGUE_LOCK:
        depth = len(_prologue_saved)
        original = module.branched_error_if
        _prologue_saved.append(original)

        def branched_error_if(x, pred, index, msgs, *, on_error="default"):
            return original(x, pred, index, msgs,
                            on_error="nan" if on_error == "default" else on_error)

        module.branched_error_if = branched_error_if
        try:
            yield
        finally:
            while len(_prologue_saved) > depth:
                end_diffrax_prologue()


@contextlib.contextmanager
def outside_diffrax_prologue():
    """Suspend an active :func:`diffrax_checks_done_on_host` window while user code is traced.

    diffrax evaluates the vector field abstractly inside its prologue (a shape check): the
    user's Lagrangian and everything it calls must see equinox as it is, or a ``jax.jit`` helper
    of theirs with an ``eqx.error_if`` would be traced (and cached by JAX) without its check.
    jaxlag's vector field wraps its evaluation in this context."""
    module = _equinox_errors()
    with _PROLOGUE_LOCK:
        if not _prologue_saved or module is None:
            yield
            return
        patched = module.branched_error_if
        module.branched_error_if = _prologue_saved[-1]
        try:
            yield
        finally:
            module.branched_error_if = patched


def end_diffrax_prologue() -> None:
    """End the innermost :func:`diffrax_checks_done_on_host` window (no-op outside one)."""
    with _PROLOGUE_LOCK:
        if _prologue_saved:
            module = _equinox_errors()
            original = _prologue_saved.pop()
            if module is not None:
                module.branched_error_if = original


def _equinox_errors():
    """equinox's private error module if it still has what this relies on, else None."""
    try:
        from equinox import _errors
    except ImportError:  # pragma: no cover - equinox reorganized
        return None
    if not (isinstance(getattr(_errors, "EQX_ON_ERROR", None), str)
            and callable(getattr(_errors, "branched_error_if", None))
            and getattr(_errors.error_if, "__module__", None) == _errors.__name__):
        return None
    return _errors


# -------------------------------------------------------------------- diffrax's 100 ULPs below t1
_ULP_LOCK = threading.RLock()
_ulp_window = {"depth": 0, "original": None, "chains": {}}


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _steps_before(x, steps, original):
    """``original`` (equinox's ``prevbefore``) applied ``steps`` times to ``x``, as a loop."""
    return jax.lax.fori_loop(0, steps, lambda _, y: original(y), x)


@_steps_before.defjvp
def _steps_before_jvp(original, primals, tangents):
    x, steps = primals
    return _steps_before(x, steps, original), tangents[0]  # prevbefore's tangent: identity


_steps_before_jit = jax.jit(_steps_before, static_argnums=2)


@contextlib.contextmanager
def ulp_chains_as_loops():
    """While tracing a ``diffrax.diffeqsolve``, compile chains of ``prevbefore`` as one loop.

    diffrax computes the threshold ``t1 − 100 ULPs`` (above which a step is clipped to ``t1``)
    as 100 chained calls of ``equinox.internal.prevbefore``: about 1500 scalar HLO operations
    in every solve program, and about 0.25 s of XLA compile time each (more once pushed
    forward for ``jax.grad``), for one number. Inside this context ``prevbefore`` is replaced by
    an exact equivalent: applied to ``x`` it returns ``original`` looped once over ``x``;
    applied to a result ``r`` it returned itself (``k`` steps from a base ``b``) it returns the
    loop of ``k + 1`` steps from ``b``. The loop runs the original function, so every value,
    denormals and signed zeros included, is bit-for-bit the same; the intermediate results of a
    chain are no longer used and XLA removes them. The step count is an argument of one jitted
    loop, traced once per dtype. Outside the context equinox is untouched; without
    ``equinox.internal.prevbefore`` (equinox reorganized) nothing is patched.
    """
    import equinox.internal as eqxi

    with _ULP_LOCK:
        original = _ulp_window["original"] if _ulp_window["depth"] else getattr(
            eqxi, "prevbefore", None)
        if original is not None and _ulp_window["depth"] == 0:
            _ulp_window["original"] = original
            chains = _ulp_window["chains"]

            def prevbefore(x):
                entry = chains.get(id(x))
                base, steps = (entry[1], entry[2]) if entry and entry[0] is x else (x, 0)
                result = _steps_before_jit(base, jnp.asarray(steps + 1, jnp.int32), original)
                chains[id(result)] = (result, base, steps + 1)
                return result

            eqxi.prevbefore = prevbefore
        if original is not None:
            _ulp_window["depth"] += 1
    if original is None:  # equinox reorganized: nothing to replace
        yield
        return
    # Not held while tracing: windows of other threads overlap (the last one out restores
    # equinox; the replacement is exact, so code outside a window may meet it meanwhile).
    try:
        yield
    finally:
        with _ULP_LOCK:
            _ulp_window["depth"] -= 1
            if _ulp_window["depth"] == 0:
                eqxi.prevbefore = _ulp_window["original"]
                _ulp_window["chains"].clear()
