"""The one calling convention for every user-supplied function.

jaxlag passes the state positionally and the rest by keyword:

* functions of the full state -- the Lagrangian ``L``, a Rayleigh dissipation function ``R``,
  external generalized forces ``Q`` -- are called as ``fn(q, qd, t=t, args=args)``;
* functions of the configuration only -- holonomic constraints ``f``, Pfaffian ``A`` and ``b`` --
  are called as ``fn(q, t=t, args=args)``.

``t`` and ``args`` are passed only when the function declares a parameter of that name (or
``**kwargs``), so ``def L(q, qd)``, ``def L(q, qd, args)``, ``def L(q, qd, t)`` and
``def L(q, qd, t, args)`` all work without ceremony. ``args`` is any pytree of parameters:
``jax.grad`` and ``jax.vmap`` flow through it. Closures over traced values work too.

The signature is read once, when the function is wrapped, with `inspect.signature`.
"""

import inspect
from collections.abc import Callable
from typing import Any, overload

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

_EXTRA_NAMES = ("t", "args")


def _parse_signature(
    fn: Callable, n_state: int, role: str, extra_names: tuple[str, ...] = _EXTRA_NAMES
) -> tuple[str, ...]:
    """Return the keywords among ``extra_names`` that ``fn`` declares (after its state)."""
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        # Builtins and some C callables have no signature: assume the bare state form.
        return ()
    positional = [
        p for p in signature.parameters.values() if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
    ]
    has_var_positional = any(p.kind == p.VAR_POSITIONAL for p in signature.parameters.values())
    has_var_keyword = any(p.kind == p.VAR_KEYWORD for p in signature.parameters.values())
    state_names = "q, qd" if n_state == 2 else "q"
    if positional and positional[0].name == "t":
        raise TypeError(
            f"The {role} {fn!r} takes `t` as its first parameter. jaxlag's convention passes the "
            f"state first: write it as `{role}({state_names}, t, args)` (t and args are optional "
            "and passed by keyword)."
        )
    if len(positional) < n_state and not has_var_positional:
        raise TypeError(
            f"The {role} {fn!r} must accept {n_state} positional argument(s) ({state_names}); "
            f"its signature is {signature}."
        )
    state_params = positional[:n_state]
    rest = [p for p in signature.parameters.values() if p not in state_params]
    takes = {name: has_var_keyword for name in extra_names}
    for p in rest:
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
            continue
        if p.name in extra_names:
            takes[p.name] = True
        elif p.default is p.empty:
            raise TypeError(
                f"The {role} {fn!r} has a required parameter `{p.name}` that jaxlag cannot fill. "
                f"jaxlag calls it as `{role}({state_names}, t=t, args=args)`, passing "
                f"{', '.join(extra_names)} only if declared; put your parameters in `args` (any "
                "pytree) or close over them."
            )
    return tuple(name for name in extra_names if takes[name])


class UserFunction(eqx.Module):
    """A user function wrapped once so that jaxlag can call it uniformly.

    Calling ``wrapped(*state, t=t, args=args)`` forwards ``t`` and ``args`` by keyword only if
    the user's function declared them. The user's function is an ordinary (non-static) field, so a
    function that is itself a pytree of arrays (an ``eqx.Module``, a neural network) is
    differentiated through like any other leaf.
    """

    fn: Callable
    keywords: tuple = eqx.field(static=True)
    role: str = eqx.field(static=True)

    def __call__(self, *state: Any, **available: Any) -> Any:
        keywords = {name: available[name] for name in self.keywords}
        if "args" not in keywords or keywords["args"] is not None:
            return self.fn(*state, **keywords)
        try:
            return self.fn(*state, **keywords)
        except (TypeError, AttributeError, KeyError) as error:
            # Runs while tracing only: no cost in the compiled program.
            raise TypeError(
                f"The {self.role} {self.fn!r} declares `args` and failed with args=None "
                f"({type(error).__name__}: {error}). Pass the parameters it reads, e.g. "
                "jl.simulate(system, q0, qd0, ts, args={...})."
            ) from error


@overload
def _wrap(fn: None, role: str, n_state: int, extra_names: tuple[str, ...] = ...) -> None: ...
@overload
def _wrap(fn: Callable, role: str, n_state: int, extra_names: tuple[str, ...] = ...) -> UserFunction: ...
@overload
def _wrap(
    fn: Callable | None, role: str, n_state: int, extra_names: tuple[str, ...] = ...
) -> UserFunction | None: ...
def _wrap(
    fn: Callable | None, role: str, n_state: int, extra_names: tuple[str, ...] = _EXTRA_NAMES
) -> UserFunction | None:
    if fn is None:
        return None
    if isinstance(fn, UserFunction):
        return fn
    if not callable(fn):
        raise TypeError(f"The {role} must be callable, got {type(fn).__name__}.")
    return UserFunction(fn, _parse_signature(fn, n_state, role, extra_names), role)


@overload
def wrap_state_function(fn: None, role: str) -> None: ...
@overload
def wrap_state_function(fn: Callable, role: str) -> UserFunction: ...
@overload
def wrap_state_function(fn: Callable | None, role: str) -> UserFunction | None: ...
def wrap_state_function(fn: Callable | None, role: str) -> UserFunction | None:
    """Wrap ``fn(q, qd, [t], [args])`` (Lagrangian, dissipation, forces, velocity constraints)."""
    return _wrap(fn, role, 2)


@overload
def wrap_configuration_function(fn: None, role: str) -> None: ...
@overload
def wrap_configuration_function(fn: Callable, role: str) -> UserFunction: ...
@overload
def wrap_configuration_function(fn: Callable | None, role: str) -> UserFunction | None: ...
def wrap_configuration_function(fn: Callable | None, role: str) -> UserFunction | None:
    """Wrap ``fn(q, [t], [args])`` (holonomic constraints)."""
    return _wrap(fn, role, 1)


def wrap_event_function(fn: Callable, role: str = "event condition") -> UserFunction:
    """Wrap ``c(q, qd, [t], [args], [multipliers])`` (event conditions)."""
    return _wrap(fn, role, 2, _EXTRA_NAMES + ("multipliers",))


_HOST_VALUES = (np.ndarray, np.generic, float, int, complex, bool, list, tuple)


def as_jax_array(x, dtype=None) -> jax.Array:
    """``jnp.asarray(x, dtype)``, without compiling anything for host values.

    JAX compiles a small program for ``jnp.asarray`` of a NumPy array (a copy, once per shape)
    and for a change of dtype (a conversion, once per dtype): tens of milliseconds each in a
    fresh process. Host values (NumPy arrays and scalars, Python numbers and lists) are
    converted on the host and transferred instead; the dtype is canonicalized as JAX does
    (``float64`` becomes ``float32`` without ``jax_enable_x64``). JAX arrays and tracers go
    through ``jnp.asarray``.
    """
    if isinstance(x, _HOST_VALUES):
        host = np.asarray(x) if dtype is None else np.asarray(x, dtype)
        return jax.device_put(host.astype(jax.dtypes.canonicalize_dtype(host.dtype), copy=False))
    return jnp.asarray(x, dtype=dtype)


def host_to_jax(x) -> jax.Array:
    """``jnp.asarray(x)`` without compiling anything for host values: NumPy values as
    `as_jax_array` converts them, Python scalars transferred with JAX's weak type (as
    ``jnp.asarray`` gives them, so that ``9.81`` does not promote a float32 computation)."""
    if isinstance(x, (bool, int, float, complex)):
        return jax.device_put(x)
    if isinstance(x, (np.ndarray, np.generic)):
        return as_jax_array(x)
    return jnp.asarray(x)


def as_float_state(q0, qd0):
    """Initial coordinates and velocities as floating-point JAX arrays (ints are promoted)."""
    q0 = as_jax_array(q0)
    if not jnp.issubdtype(q0.dtype, jnp.floating):
        q0 = q0.astype(jnp.result_type(float))
    qd0 = as_jax_array(qd0)
    if not jnp.issubdtype(qd0.dtype, jnp.floating):
        qd0 = qd0.astype(q0.dtype)
    return q0, qd0


def as_array_leaves(tree, dtype=None):
    """Python floats and NumPy arrays become (strongly typed) JAX arrays.

    Used on ``args`` before compiled entry points, so that calling again with new parameter
    values reuses the compiled program (a Python float would be a static, hashed value), and so
    that ``1.0`` and ``np.float64(1.0)`` share one trace. Weakly typed JAX values (a Python float
    that ``jax.grad`` made an array) become strongly typed the same way, so that a derivative
    traces the programs of the plain call (not a second variant). Python ints and bools stay
    static: they may drive Python control flow in user functions.

    ``dtype``: the floating dtype of the state. A Python float (or a weakly typed JAX float)
    takes it, as JAX's weak typing would, so that ``args={"g": 9.81}`` in a float32 simulation
    is float32 and does not promote the user's functions to float64. NumPy and strongly typed
    JAX arrays keep the dtype they were given.
    """

    def convert(x):
        if dtype is not None and isinstance(x, float):
            return as_jax_array(x, dtype)
        if isinstance(x, (float, complex, np.ndarray, np.floating)):
            return as_jax_array(x, np.result_type(x))  # converted on the host, no compilation
        if isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jnp.inexact) and jax.typeof(x).weak_type:
            target = dtype if dtype is not None and jnp.issubdtype(x.dtype, jnp.floating) else x.dtype
            return jax.lax.convert_element_type(x, target)
        return x

    return jax.tree.map(convert, tree)


def as_jit_inputs(t, args, dtype):
    """``(t, args)`` for a jitted function of the state: a Python-number ``t`` as a (weakly typed)
    array and the Python floats of ``args`` as arrays (`as_array_leaves`), so that a new time or
    parameter value is an input of the compiled program rather than a static value that compiles
    it anew."""
    if isinstance(t, (int, float)):
        t = jnp.asarray(t)
    return t, as_array_leaves(args, dtype)
