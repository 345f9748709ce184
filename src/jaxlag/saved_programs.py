"""Compiled programs saved across processes: the second run of a script skips tracing.

JAX's persistent compilation cache (:mod:`jaxlag.compilation`) saves the XLA compile of a
program, but every new process still traces and lowers it first: for ``jl.simulate`` of the
README's first example that is 0.35-0.45 s of tracing and 0.1 s of lowering, for its
``jax.grad`` as much again, more than the rest of the script. jaxlag therefore also keeps its
own, higher-level cache for its solver programs (``simulate``'s solve, with events and contact
too, the forward sensitivities of ``jax.grad``) and a trajectory's derived quantities: when such
a program is called with concrete values (no
``jit``/``vmap``/``grad`` trace around the call), the compiled executable is looked up on disk
by a *fingerprint* of everything that determines it and, when found, loaded and called (about
0.05 s) instead of being traced, lowered and compiled.

**The fingerprint** (a SHA-256) covers:

* the environment: jaxlag's own source files (their bytes), the versions of Python, jax,
  jaxlib, diffrax, equinox, lineax, optimistix and numpy, the backend, its devices and the
  host CPU, the environment variables of these libraries and XLA (``XLA_FLAGS``,
  ``EQX_ON_ERROR``, ...), jaxlag's compiler options and JAX's configuration values;
* the program's inputs as its trace would see them: every array by shape, dtype and weak type
  (values are inputs of the program, not part of it); every other value (Python numbers,
  strings, options, diffrax's solver and controller, jaxlag's modules) by type and content,
  walked field by field. Types and functions are accepted only from jaxlag and the libraries
  above (their code is covered by the versions and the source digest); anything else (a class or
  function of the user's own, other than the system's functions below) makes the call
  *uncacheable*: it runs through ``jax.jit`` as usual;
* the user's functions (Lagrangian, constraints, dissipation, forces, the conditions of
  ``jl.Event``, ``jl.fit``'s observation function): by their **jaxpr** at the call's shapes
  (``jax.make_jaxpr`` of these functions, a few milliseconds) with the values of the constants
  they close over. A jaxpr is exactly what these functions contribute to the program, whatever
  Python they are written in (globals read, helper functions, closures). Functions that a jaxpr
  holds but prints by name only (custom derivative rules, callbacks) are walked like the inputs,
  so a user's own rule, and in practice every ``custom_jvp`` function, JAX's too
  (``jax.nn.relu``, ``softplus``, ``jnp.sinc``), makes the call uncacheable; so does a jaxpr
  whose text names an object by its address.

Anything not in the fingerprint cannot change the program. What it cannot see is a user function
that behaves differently when traced by the solver than when traced alone (e.g. one that
branches on the kind of tracer it is given); ``JAXLAG_COMPILATION_CACHE=0`` turns this cache
off with JAX's, ``JAXLAG_PROGRAM_CACHE=0`` this one alone.

**What is saved** (``$XDG_CACHE_HOME/jaxlag/programs``, default ``~/.cache/jaxlag/programs``;
0.3-1 MB per program): the executable (``jax.experimental.serialize_executable``, the mechanism
behind JAX's own cache) and the output's non-array structure, pickled with every object that
came from the inputs (the system, its functions) recorded by position and restored to the
caller's own objects on loading. Programs with host callbacks are never saved. A file that
cannot be read is ignored and replaced.

Saved programs are compiled outside JAX's persistent cache (:func:`_compiling_for_saving`): an
executable that JAX's cache *loaded* serializes without the machine code of its fusions, so a
later process that loads it fails at run time ("Function convert_multiply_fusion not found",
JAX 0.10 on the CPU). JAX's cache therefore does not store these programs (they are stored
here), and an executable it returns anyway (an entry from an older jaxlag) is used but not
saved. A loaded executable's first call in a process waits for its result, and one that fails
to run is deleted and compiled again. Like JAX's cache, the directory holds executable code:
it must be writable by you alone.

Only on the CPU backend (:func:`_cpu_ready`): a loaded executable skips lowering, where JAX
initializes the custom calls it needs; on the CPU that is LAPACK, initialized here as
``jax.export`` does, other backends are not checked and keep ``jax.jit``.

Within one process, the programs are kept by the identity of the call's non-array inputs and
the shapes of its arrays (as ``jax.jit`` keeps them): the fingerprint is computed once per new
kind of call.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import enum
import functools
import hashlib
import importlib.metadata
import io
import os
import pickle
import platform
import sys
import tempfile
import threading
import types
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import numpy as np

from . import compilation

#: Version of the files' layout: a change makes older files misses.
FORMAT = 1
#: Packages whose types and functions may appear in a fingerprinted call (their code is covered
#: by the versions and jaxlag's source digest).
TRUSTED_PACKAGES = ("jaxlag", "diffrax", "equinox", "lineax", "optimistix", "jax", "jaxlib",
                    "jaxtyping", "numpy", "builtins", "functools", "operator", "math")
_VERSIONED = ("jax", "jaxlib", "diffrax", "equinox", "lineax", "optimistix", "numpy")
_SYSTEM_FUNCTIONS = ("lagrangian", "holonomic", "velocity_constraints", "dissipation", "forces")
_MEMORY_SIZE = 64
#: Environment variables that can change how a program is traced or compiled (equinox reads
#: ``EQX_ON_ERROR`` when tracing its checks).
_READ_VARIABLES = ("XLA_", "JAX_", "EQX_", "JAXLAG_", "DIFFRAX_", "LINEAX_", "OPTIMISTIX_")
#: Counts in this process (read by tests and benchmarks): programs ``loaded`` from disk,
#: ``compiled`` (then ``saved`` unless they hold host callbacks, or JAX's cache returned the
#: executable: ``loaded_by_jax_cache``), loaded ones ``discarded`` because they failed to run,
#: and calls found ``uncacheable``.
statistics = collections.Counter()


class Uncacheable(Exception):
    """The call holds something the fingerprint cannot describe: it runs through ``jax.jit``."""


def enabled() -> bool:
    """Whether programs are saved and loaded: on the CPU backend (see :func:`_cpu_ready`),
    with ``JAXLAG_COMPILATION_CACHE`` and ``JAXLAG_PROGRAM_CACHE`` not switched off and a cache
    directory that can be created."""
    if compilation._switched_off("JAXLAG_COMPILATION_CACHE") or \
            compilation._switched_off("JAXLAG_PROGRAM_CACHE"):
        return False
    return _cpu_ready() and directory() is not None


@functools.cache
def _cpu_ready() -> bool:
    """Whether the default backend is the CPU and its LAPACK kernels are initialized.

    A loaded executable is not lowered, and lowering is where JAX initializes the CPU's LAPACK
    custom calls (``lax.linalg.initialize_lapack``; ``jax.export`` calls it before running a
    deserialized module for the same reason): a loaded solver with a Cholesky or LU factorization
    would otherwise crash the process. JAX has no public API for it, so without it nothing is
    loaded. Other backends are left to ``jax.jit`` (their custom calls are not checked here)."""
    if jax.default_backend() != "cpu":
        return False
    try:
        from jax._src.lax import linalg

        linalg.initialize_lapack()
    except Exception:  # noqa: BLE001 - JAX moved it: do not load executables
        return False
    return True


def directory() -> str | None:
    """The directory of saved programs, created if needed (None if it cannot be)."""
    return _made(compilation.user_cache_path("programs"))


@functools.cache
def _made(path: str) -> str | None:
    try:
        os.makedirs(path, mode=0o700, exist_ok=True)
    except OSError:
        return None
    return path


# ------------------------------------------------------------------------------- environment
@functools.cache
def _static_environment() -> str:
    """What cannot change within a process: source digest, versions, host, devices."""
    digest = hashlib.sha256()
    root = os.path.dirname(os.path.abspath(__file__))
    for folder, subfolders, files in sorted(os.walk(root)):
        subfolders[:] = sorted(d for d in subfolders if d != "__pycache__")
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                digest.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as file:
                    digest.update(hashlib.sha256(file.read()).digest())
    versions = []
    for package in _VERSIONED:
        try:
            versions.append((package, importlib.metadata.version(package)))
        except importlib.metadata.PackageNotFoundError:
            versions.append((package, None))
    device = jax.devices()[0]
    parts = [
        FORMAT, digest.hexdigest(), sys.version, platform.machine(), platform.platform(),
        versions, device.platform, getattr(device, "device_kind", None),
        getattr(device.client, "platform_version", None), jax.device_count(), _cpu_flags(),
    ]
    return repr(parts)


def _cpu_flags() -> str:
    """The host CPU's model and instruction-set flags (an executable compiled for the CPU uses
    them): Linux's ``/proc/cpuinfo``, else the platform's processor name."""
    try:
        with open("/proc/cpuinfo") as file:
            lines = [line for line in file if line.startswith(("model name", "flags"))]
        return hashlib.sha256("".join(sorted(set(lines))).encode()).hexdigest()
    except OSError:
        return platform.processor()


def _environment() -> str:
    """:func:`_static_environment` and what can change during a process: JAX's configuration,
    ``XLA_FLAGS``, jaxlag's compiler options."""
    config = sorted((name, repr(value)) for name, value in jax.config.values.items()
                    if isinstance(value, (bool, int, float, str, type(None))))
    variables = sorted((name, value) for name, value in os.environ.items()
                       if name.startswith(_READ_VARIABLES))
    return repr([_static_environment(), config, variables,
                 sorted(compilation.compiler_options().items())])


# ------------------------------------------------------------------------------- fingerprint
def _trusted(module: str | None) -> bool:
    return module is not None and module.split(".")[0] in TRUSTED_PACKAGES


@functools.cache
def _module_singletons(module_name: str) -> dict[int, str]:
    """Module-level objects of a trusted module by identity (equinox's ``MISSING``, diffrax's
    default functions): recorded by name, so that loading restores the very object."""
    module = sys.modules.get(module_name)
    if module is None:
        return {}
    return {id(value): name for name, value in vars(module).items()
            if not isinstance(value, (bool, int, float, str, bytes, type(None)))}


def _global_name(obj) -> tuple[str, str] | None:
    """``(module, name)`` if ``obj`` is a module-level object of a trusted module."""
    module = getattr(type(obj), "__module__", None)
    if not _trusted(module):
        return None
    name = _module_singletons(module).get(id(obj))
    if name is not None and getattr(sys.modules[module], name, None) is obj:
        return module, name
    return None


class _Fingerprint:
    """Walks a call's inputs into a list of tokens (see the module docstring) and records every
    non-primitive object met, in order (the table that pickled outputs refer to)."""

    def __init__(self):
        self.tokens: list = []
        self.table: list = []
        self._seen: dict[int, int] = {}
        self.user_functions: set[int] = set()

    def _remember(self, obj) -> bool:
        """Record ``obj``; False if it was met before (a reference token is written)."""
        index = self._seen.get(id(obj))
        if index is not None:
            self.tokens.append(("ref", index))
            return False
        self._seen[id(obj)] = len(self.table)
        self.table.append(obj)
        return True

    def visit(self, obj) -> None:
        tokens = self.tokens
        if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
            tokens.append((type(obj).__name__, repr(obj)))
            return
        if isinstance(obj, jax.core.Tracer):
            raise Uncacheable("a traced value")
        if isinstance(obj, (jax.Array, np.ndarray, np.generic)):
            tokens.append(("array", np.shape(obj), np.dtype(obj.dtype).str,
                           bool(getattr(obj, "weak_type", False))))
            return
        if isinstance(obj, jax.core.ShapedArray):  # in closures of JAX's own rules
            tokens.append(("aval", obj.shape, np.dtype(obj.dtype).str, obj.weak_type))
            return
        if isinstance(obj, np.dtype):
            tokens.append(("dtype", obj.str))
            return
        if isinstance(obj, (tuple, list)):
            tokens.append((type(obj).__name__, len(obj)))
            for item in obj:
                self.visit(item)
            return
        if isinstance(obj, dict):
            if type(obj) not in (dict, collections.OrderedDict):
                raise Uncacheable(f"a mapping of type {type(obj).__name__}")
            items = sorted(obj.items(), key=lambda item: repr(item[0]))
            tokens.append(("dict", [repr(key) for key, _ in items]))
            for _, value in items:
                self.visit(value)
            return
        if isinstance(obj, jax.tree_util.PyTreeDef):
            self._visit_treedef(obj)
            return
        if isinstance(obj, type):
            if not _trusted(obj.__module__):
                raise Uncacheable(f"the class {obj.__qualname__} of {obj.__module__}")
            tokens.append(("type", obj.__module__, obj.__qualname__))
            return
        if not self._remember(obj):
            return
        name = _global_name(obj)
        if name is not None:
            tokens.append(("global",) + name)
            return
        if isinstance(obj, enum.Enum):
            self.visit(type(obj))
            tokens.append(("enum", obj.name))
            return
        if isinstance(obj, functools.partial):
            tokens.append(("partial",))
            for part in (obj.func, obj.args, dict(obj.keywords)):
                self.visit(part)
            return
        if isinstance(obj, types.MethodType):
            tokens.append(("method",))
            self.visit(obj.__self__)
            self.visit(obj.__func__)
            return
        if isinstance(obj, types.FunctionType):
            self._visit_function(obj)
            return
        if isinstance(obj, eqx.Module):
            self._visit_module(obj)
            return
        if callable(obj) and _trusted(getattr(obj, "__module__", None)):
            # A trusted library's callable object (a jitted function, a ufunc) by its name.
            module, qualname = obj.__module__, getattr(obj, "__qualname__", None)
            if qualname is None or _lookup(module, qualname) is not obj:
                raise Uncacheable(f"the callable {obj!r}")
            tokens.append(("named", module, qualname))
            return
        raise Uncacheable(f"a {type(obj).__module__}.{type(obj).__qualname__} object")

    def _visit_function(self, fn) -> None:
        if not _trusted(fn.__module__):
            raise Uncacheable(f"the function {fn.__qualname__} of {fn.__module__}")
        # Code from a trusted module (covered by the versions / source digest); what it closed
        # over and its defaults are walked.
        self.tokens.append(("function", fn.__module__, fn.__qualname__))
        cells = [cell.cell_contents for cell in (fn.__closure__ or ())]
        for part in (cells, fn.__defaults__, fn.__kwdefaults__):
            self.visit(part)

    def _visit_module(self, module) -> None:
        kind = type(module)
        if not _trusted(kind.__module__):
            raise Uncacheable(f"the module class {kind.__qualname__} of {kind.__module__}")
        self.tokens.append(("module", kind.__module__, kind.__qualname__))
        from .conventions import UserFunction
        from .events import Event
        from .fit import _Model
        from .system import System

        if isinstance(module, UserFunction):
            raise Uncacheable("a user function outside a jl.System, jl.Event or fit model")
        covered = (_SYSTEM_FUNCTIONS if isinstance(module, System)
                   else ("condition",) if isinstance(module, Event)
                   else ("observe",) if isinstance(module, _Model) else ())
        for field in dataclasses.fields(module):
            value = getattr(module, field.name, _UNSET)
            self.tokens.append(("field", field.name))
            if field.name in covered and isinstance(value, UserFunction):
                # Covered by the jaxpr of the system's functions (SavedProgram._fingerprint).
                self._remember(value)
                if value.fn is not None:  # None: a partitioned copy's (arrays apart)
                    self._remember(value.fn)
                    self.user_functions.add(id(value.fn))
                self.tokens.append(("user function", value.fn is None, value.keywords,
                                    value.role))
            elif value is _UNSET:
                self.tokens.append(("unset",))
            else:
                self.visit(value)

    def _visit_treedef(self, treedef) -> None:
        children = treedef.children()
        data = treedef.node_data()
        if data is None:
            self.tokens.append(("leaf" if treedef.num_leaves == 1 else "none",))
            return
        kind, aux = data
        self.visit(kind)
        self.tokens.append(("node", len(children)))
        self.visit(aux)
        for child in children:
            self._visit_treedef(child)


_UNSET = object()


def _lookup(module: str, qualname: str):
    obj = sys.modules.get(module)
    for part in qualname.split("."):
        obj = getattr(obj, part, None)
    return obj


def _user_function_values(system, q, qd, t, args, events=(), observers=()) -> list:
    """The system's functions, the conditions of ``events`` (:class:`jaxlag.Event`) and the
    ``observers`` (``jl.fit``'s observation function) evaluated at one state (what their jaxpr
    fingerprints)."""
    state = {"lagrangian": (q, qd), "holonomic": (q,), "velocity_constraints": (q, qd),
             "dissipation": (q, qd), "forces": (q, qd)}
    values = [getattr(system, name)(*values, t=t, args=args) for name, values in state.items()
              if getattr(system, name) is not None]
    for event in events:
        available = {"t": t, "args": args}
        if "multipliers" in event.condition.keywords:
            available["multipliers"] = system.multipliers(q, qd, t, args)
        values.append(event.condition(q, qd, **available))
    values.extend(observe(q, qd, t=t, args=args) for observe in observers)
    return values


def _jaxpr_fingerprint(system, q, qd, t, args, events=(), observers=()) -> tuple[list, set[int]]:
    """The text of the jaxpr of ``system``'s functions (and the event conditions, observers)
    at this state and the digests of the constants they close over; and the identities of the
    functions it covers."""
    dynamic, static = eqx.partition((system, q, qd, t, args, tuple(events), tuple(observers)),
                                    _array_or_shape)
    closed = jax.make_jaxpr(
        lambda d: _user_function_values(*eqx.combine(d, static)))(dynamic)
    text = str(closed.jaxpr)
    if " at 0x" in text:
        raise Uncacheable("a function whose jaxpr names an object by its address")
    # Functions held by equations (custom_jvp/custom_vjp rules, callbacks, checkpoint policies)
    # are printed by name only: walked like the inputs (a user's own is uncacheable).
    rules = _Fingerprint()
    for function in _equation_functions(closed.jaxpr):
        rules.visit(function)
    constants = []
    for value in closed.consts:
        if isinstance(value, jax.core.Tracer):
            raise Uncacheable("a closure over a traced value")
        array = np.asarray(value)
        constants.append((array.shape, array.dtype.str,
                          hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()))
    covered = {id(getattr(system, name).fn) for name in _SYSTEM_FUNCTIONS
               if getattr(system, name) is not None}
    covered.update(id(event.condition.fn) for event in events)
    covered.update(id(observe.fn) for observe in observers)
    return [text, constants, rules.tokens], covered


def _array_or_shape(x) -> bool:
    return eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)


def _equation_functions(jaxpr):
    """The Python callables among the parameters of ``jaxpr``'s equations, nested ones too."""
    from jax.extend import core

    for equation in jaxpr.eqns:
        for value in equation.params.values():
            for item in value if isinstance(value, (tuple, list)) else (value,):
                if isinstance(item, core.ClosedJaxpr):
                    yield from _equation_functions(item.jaxpr)
                elif isinstance(item, core.Jaxpr):
                    yield from _equation_functions(item)
                elif hasattr(item, "call_wrapped"):  # JAX's WrappedFun: its function
                    yield item.f
                elif callable(item) and not isinstance(item, type):
                    yield item


# ------------------------------------------------------------------------------- pickling
class _Pickler(pickle.Pickler):
    """Pickles a program's output structure; objects from the inputs by their table position,
    trusted module-level objects by name."""

    def __init__(self, file, table):
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self._positions = {id(obj): i for i, obj in enumerate(table)}

    def persistent_id(self, obj):
        if obj is None or isinstance(obj, (bool, int, float, str, bytes, type)):
            return None
        position = self._positions.get(id(obj))
        if position is not None:
            return ("input", position)
        name = _global_name(obj)
        if name is not None:
            return ("global",) + name
        return None


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, table):
        super().__init__(file)
        self._table = table

    def persistent_load(self, pid):
        if pid[0] == "input":
            return self._table[pid[1]]
        if pid[0] == "global":
            return getattr(sys.modules[pid[1]], pid[2])
        raise pickle.UnpicklingError(f"unknown reference {pid!r}")


# ------------------------------------------------------------------------------- programs
@dataclasses.dataclass
class _Entry:
    """A compiled program: flat arrays in, flat arrays out; the output is ``out_tree`` with the
    arrays at ``positions`` of its leaves and ``template``'s other leaves."""

    compiled: Any
    out_tree: Any
    template: list
    positions: tuple
    out_shapes: list
    loaded_from: str | None = None  # the file, until its first call in this process has run

    def outputs(self, values):
        leaves = list(self.template)
        for position, value in zip(self.positions, values):
            leaves[position] = value
        return jax.tree.unflatten(self.out_tree, leaves)

    def __call__(self, arrays):
        return self.outputs(self.compiled(*arrays))

    def shapes(self):
        return self.outputs(self.out_shapes)


_ARRAYS = (jax.Array, np.ndarray, np.generic)


class SavedProgram:
    """A jaxlag program (``fn``, a function of pytrees) compiled by :func:`compilation.filter_jit`
    and, for calls with concrete values, saved and loaded as the module docstring describes.

    ``state_of(*args)`` returns ``(system, q, qd, t, args[, events[, observers]])`` from the
    call's arguments: the state at which the system's functions (and the events' conditions,
    the fit's observation function) are fingerprinted by their jaxpr (arrays or
    ``jax.ShapeDtypeStruct``)."""

    def __init__(self, fn: Callable, state_of: Callable):
        functools.update_wrapper(self, fn)
        self._fn = fn
        self._jit = compilation.filter_jit(fn)
        self._state_of = state_of
        self._memory: collections.OrderedDict = collections.OrderedDict()
        self._lock = threading.Lock()
        self.name = f"{fn.__module__}.{fn.__qualname__}"

    def __call__(self, *args):
        found = self._entry(args)
        if found is None:
            return self._jit(*args)
        entry, arrays = found
        if entry.loaded_from is not None:
            return self._first_call_of_loaded(entry, arrays, args)
        return entry(arrays)

    def _first_call_of_loaded(self, entry: _Entry, arrays, args):
        """A loaded executable's first call in this process waits for its result: should it
        fail to run (a file written by a jaxlag whose executables did not survive
        serialization), the file is deleted and the program compiled and run as usual."""
        try:
            values = jax.block_until_ready(entry.compiled(*arrays))
        except Exception:  # noqa: BLE001 - the compiled program runs next, and raises its own
            statistics["discarded"] += 1
            _discarded.add(entry.loaded_from)  # never loaded again by this process
            with contextlib.suppress(OSError):
                os.unlink(entry.loaded_from)
            with self._lock:
                for key in [k for k, v in self._memory.items() if v is entry]:
                    del self._memory[key]
            return self(*args)
        entry.loaded_from = None
        return entry.outputs(values)

    def eval_shape(self, *args):
        """``jax.eval_shape`` of the program; for a saved program its stored output shapes (no
        trace). Getting them compiles or loads the program, which a call then reuses."""
        found = self._entry(args)
        if found is None:
            return eqx.filter_eval_shape(self._jit, *args)
        return found[0].shapes()

    def lower(self, *args):
        return self._jit.lower(*args)

    # -- lookup
    def _entry(self, args):
        """``(entry, arrays)`` for a cacheable call with concrete values, else None."""
        if not enabled() or not compilation.no_transformation_active() or _debugging():
            return None
        leaves, treedef = jax.tree.flatten(args)
        arrays, signature = [], []
        device = _default_device()
        for leaf in leaves:
            if isinstance(leaf, _ARRAYS):
                if isinstance(leaf, jax.core.Tracer):
                    return None
                if isinstance(leaf, jax.Array) and leaf.devices() != {device}:
                    return None  # placed elsewhere: jax.jit places the program
                arrays.append(leaf)
                signature.append((np.shape(leaf), leaf.dtype,
                                  bool(getattr(leaf, "weak_type", False))))
            else:
                signature.append(leaf)  # as jax.jit keys a static value (a tuple is no leaf)
        key = (treedef, tuple(signature))
        try:
            hash(key)
        except TypeError:
            return None
        with self._lock:
            entry = self._memory.get(key, _UNSET)
            if entry is not _UNSET:
                self._memory.move_to_end(key)
        if entry is _UNSET:
            entry = self._load_or_compile(args, leaves, treedef, arrays)
            with self._lock:
                self._memory[key] = entry
                while len(self._memory) > _MEMORY_SIZE:
                    self._memory.popitem(last=False)
        return None if entry is None else (entry, arrays)

    def _fingerprint(self, args) -> tuple[str, list]:
        walk = _Fingerprint()
        walk.visit(args)
        jaxpr, covered = _jaxpr_fingerprint(*self._state_of(*args))
        if not walk.user_functions <= covered:
            raise Uncacheable("functions of a system other than the one simulated")
        text = repr([_environment(), self.name, walk.tokens, jaxpr])
        return hashlib.sha256(text.encode()).hexdigest(), walk.table

    def _load_or_compile(self, args, leaves, treedef, arrays):
        try:
            key, table = self._fingerprint(args)
        except Uncacheable:
            statistics["uncacheable"] += 1
            return None
        path = os.path.join(directory(), f"{key}.program")
        entry = _load(path, key, table)
        if entry is not None:
            statistics["loaded"] += 1
            return entry
        where = [i for i, leaf in enumerate(leaves) if isinstance(leaf, _ARRAYS)]
        box = {}

        def flat(*values):
            merged = list(leaves)
            for position, value in zip(where, values):
                merged[position] = value
            out_leaves, out_tree = jax.tree.flatten(self._fn(*jax.tree.unflatten(treedef, merged)))
            positions = tuple(i for i, leaf in enumerate(out_leaves) if isinstance(leaf, _ARRAYS))
            template = [None if i in positions else leaf for i, leaf in enumerate(out_leaves)]
            box.update(out_tree=out_tree, template=template, positions=positions)
            return [out_leaves[i] for i in positions]

        # JAX names the program after the function: a name of its own, so that no entry of
        # JAX's cache written for the same function compiled the usual way matches it.
        flat.__name__ = flat.__qualname__ = "saved_" + self._fn.__name__.lstrip("_")
        options = compilation.compiler_options()
        lowered = jax.jit(flat, compiler_options=options or None).lower(*arrays)
        with _compiling_for_saving() as watch:
            compiled = lowered.compile()
        shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in compiled.out_info]
        entry = _Entry(compiled, box["out_tree"], box["template"], box["positions"], shapes)
        statistics["compiled"] += 1
        if watch.loaded_by_jax:
            statistics["loaded_by_jax_cache"] += 1  # not saved: see the module docstring
        elif _storable(lowered) and _save(path, key, entry, table):
            statistics["saved"] += 1
        return entry


_watch = threading.local()


def _on_jax_event(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits" and getattr(_watch, "active", False):
        _watch.loaded_by_jax = True


@functools.cache
def _listen_to_jax_cache() -> None:
    jax.monitoring.register_event_listener(_on_jax_event)


def _no_jax_cache_writes():
    """JAX's persistent cache writes no program that compiles faster than its
    ``jax_persistent_cache_min_compile_time_secs``: infinity, in this thread, for this block."""
    try:
        from jax._src import config as jax_config

        return jax_config.persistent_cache_min_compile_time_secs(float("inf"))
    except (ImportError, AttributeError, TypeError):  # another JAX: the event below still guards
        return contextlib.nullcontext()


@contextlib.contextmanager
def _compiling_for_saving():
    """Compile a program to be saved: JAX's persistent cache writes nothing in this block, and
    ``watch.loaded_by_jax`` says whether JAX's cache returned the executable (JAX records the
    event ``/jax/compilation_cache/cache_hits`` in the compiling thread)."""
    _listen_to_jax_cache()
    _watch.active, _watch.loaded_by_jax = True, False
    try:
        with _no_jax_cache_writes():
            yield _watch
    finally:
        _watch.active = False


def _debugging() -> bool:
    """``jax.disable_jit()`` or JAX's NaN/Inf checks: ``jax.jit`` honours them, an executable
    called directly would not."""
    config = jax.config
    return bool(config.jax_disable_jit or config.jax_debug_nans or config.jax_debug_infs)


@functools.cache
def _default_device():
    return jax.devices()[0]


def _storable(lowered) -> bool:
    """Whether the program has no host callbacks or effects (which an executable cannot carry
    to another process)."""
    compile_args = getattr(getattr(lowered, "_lowering", None), "compile_args", None)
    if not isinstance(compile_args, dict) or "host_callbacks" not in compile_args:
        return False  # JAX's layout changed: do not guess
    return not (compile_args.get("host_callbacks") or compile_args.get("ordered_effects")
                or compile_args.get("unordered_effects"))


def _save(path: str, key: str, entry: _Entry, table: list) -> bool:
    from jax.experimental import serialize_executable

    temporary = None
    try:
        executable, in_tree, out_tree = serialize_executable.serialize(entry.compiled)
        buffer = io.BytesIO()
        _Pickler(buffer, table).dump((entry.out_tree, entry.template, entry.positions))
        shapes = [(s.shape, np.dtype(s.dtype).str) for s in entry.out_shapes]
        payload = pickle.dumps((FORMAT, key, executable, in_tree, out_tree, buffer.getvalue(),
                                shapes), protocol=pickle.HIGHEST_PROTOCOL)
        folder = os.path.dirname(path)
        handle, temporary = tempfile.mkstemp(dir=folder, suffix=".partial")
        with os.fdopen(handle, "wb") as file:
            file.write(payload)
        os.replace(temporary, path)
        return True
    except Exception:  # noqa: BLE001 - not saved: the next process compiles again
        if temporary is not None and os.path.exists(temporary):
            os.unlink(temporary)
        return False


_discarded: set = set()  # files whose executable failed to run in this process


def _load(path: str, key: str, table: list) -> _Entry | None:
    from jax.experimental import serialize_executable

    if path in _discarded:
        return None
    try:
        with open(path, "rb") as file:
            payload = file.read()
    except OSError:
        return None
    try:
        form, stored_key, executable, in_tree, out_tree, structure, shapes = pickle.loads(payload)
        if form != FORMAT or stored_key != key:
            return None
        out_structure, template, positions = _Unpickler(io.BytesIO(structure), table).load()
        compiled = serialize_executable.deserialize_and_load(executable, in_tree, out_tree)
        return _Entry(compiled, out_structure, template, positions,
                      [jax.ShapeDtypeStruct(shape, np.dtype(dtype)) for shape, dtype in shapes],
                      loaded_from=path)
    except Exception:  # noqa: BLE001 - unreadable or from another layout: compile again
        return None


def saved_program(state_of: Callable):
    """Decorator: :class:`SavedProgram` with ``state_of``."""
    return lambda fn: SavedProgram(fn, state_of)
