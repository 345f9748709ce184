r"""Evaluate a per-member jaxpr lane-wise: every array entry becomes one 1-D column of the batch.

A GPU kernel lowering (Pallas → Triton) wants elementwise arithmetic on 1-D blocks: no slices,
reshapes or small matrix products on ``(block, n)`` arrays, which is what ``jax.vmap`` of the
per-member equations produces. Here a per-member function is traced once to a jaxpr (shapes of one
member) and evaluated with every array represented as a NumPy *object* array of the same shape
whose entries are the member values of that entry as ``(block,)`` arrays (or Python/NumPy scalars
when they are the same for every member). Then

* elementwise primitives apply entry by entry to the columns;
* structural primitives (``slice``, ``squeeze``, ``reshape``, ``broadcast_in_dim``,
  ``concatenate``, ``transpose``, ``pad``, ``iota``, ...) are bookkeeping on the object array and
  emit no operation at all;
* ``dot_general`` and ``reduce_sum`` become sums of column products.

The result is the same arithmetic as the vmapped function, written as straight-line code on
columns. Primitives outside this set raise `NotImplementedError` (the caller falls back).
"""

import functools
import operator

import jax
import jax.core
import jax.extend.core as jcore
import jax.numpy as jnp
import numpy as np

_ELEMENTWISE = frozenset(
    """
abs acos acosh add add_any and asin asinh atan atan2 atanh cbrt ceil clamp convert_element_type
copy copy_p cos cosh div eq erf erf_inv erfc exp exp2 expm1 floor ge gt integer_pow is_finite le
lgamma log log1p logistic lt max min mul ne neg nextafter not or pow reduce_precision rem round
rsqrt select_n sign sin sinh sqrt square sub tan tanh xor
""".split()
)


def columns(x) -> np.ndarray:
    """A batched array ``(block, *shape)`` as an object array ``shape`` of ``(block,)`` columns."""
    shape = x.shape[1:]
    out = np.empty(shape, dtype=object)
    for index in np.ndindex(*shape):
        out[index] = x[(slice(None),) + index]
    return out


def constant(value) -> np.ndarray:
    """A value shared by all members (concrete or traced) as an object array of scalars."""
    if not isinstance(value, jax.Array):  # tracers are jax.Array instances too
        value = np.asarray(value)
    out = np.empty(jnp.shape(value), dtype=object)
    for index in np.ndindex(*jnp.shape(value)):
        out[index] = value[index]
    return out


def _lane_shape(entries):
    for e in entries:
        if jnp.ndim(e) == 1:
            return jnp.shape(e)
    return None


def _elementwise(primitive, params, *operands):
    shape = np.broadcast_shapes(*(o.shape for o in operands))
    operands = [np.broadcast_to(o, shape) for o in operands]
    out = np.empty(shape, dtype=object)
    for index in np.ndindex(*shape):
        entries = [o[index] for o in operands]
        lanes = _lane_shape(entries)
        if lanes is not None:
            entries = [e if jnp.ndim(e) == 1 else jnp.full(lanes, e, dtype=_dtype(e)) for e in entries]
        elif not any(isinstance(e, jax.core.Tracer) for e in entries):
            # Shared by every member and known: folded now (a kernel lowering may not accept
            # arithmetic on literals), kept as a NumPy scalar.
            with jax.ensure_compile_time_eval():
                value = primitive.bind(*[jnp.asarray(e, dtype=_dtype(e)) for e in entries], **params)
            out[index] = np.asarray(value)[()]
            continue
        else:
            entries = [jnp.asarray(e, dtype=_dtype(e)) for e in entries]
        out[index] = primitive.bind(*entries, **params)
    return out


def _dtype(entry):
    return entry.dtype if hasattr(entry, "dtype") else np.asarray(entry).dtype


def _sum(entries):
    return functools.reduce(operator.add, entries)


def _dot_general(lhs, rhs, dimension_numbers, **_):
    (lc, rc), (lb, rb) = dimension_numbers
    lf = [d for d in range(lhs.ndim) if d not in lc and d not in lb]
    rf = [d for d in range(rhs.ndim) if d not in rc and d not in rb]
    lhs = np.transpose(lhs, list(lb) + lf + list(lc))
    rhs = np.transpose(rhs, list(rb) + rf + list(rc))
    nb, nk = len(lb), len(lc)
    batch_shape = lhs.shape[:nb]
    lhs_free, rhs_free = lhs.shape[nb : lhs.ndim - nk], rhs.shape[nb : rhs.ndim - nk]
    contract = lhs.shape[lhs.ndim - nk :]
    out = np.empty(batch_shape + lhs_free + rhs_free, dtype=object)
    for b in np.ndindex(*batch_shape):
        for i in np.ndindex(*lhs_free):
            for j in np.ndindex(*rhs_free):
                terms = [lhs[b + i + k] * rhs[b + j + k] for k in np.ndindex(*contract)]
                out[b + i + j] = _sum(terms) if terms else 0.0
    return out


def _reduce(entries_op, operand, axes):
    moved = np.moveaxis(operand, axes, tuple(range(operand.ndim - len(axes), operand.ndim)))
    keep = moved.shape[: operand.ndim - len(axes)]
    out = np.empty(keep, dtype=object)
    for index in np.ndindex(*keep):
        out[index] = functools.reduce(entries_op, list(moved[index].ravel()))
    return out


def _pad(operand, padding_value, padding_config):
    value = padding_value[()]
    shape = []
    for size, (low, high, interior) in zip(operand.shape, padding_config):
        shape.append(low + high + size + max(size - 1, 0) * interior)
    out = np.empty(shape, dtype=object)
    out[...] = value
    target = []
    for size, (low, _, interior) in zip(operand.shape, padding_config):
        if low < 0:
            raise NotImplementedError("negative padding")
        target.append(slice(low, low + (size - 1) * (interior + 1) + 1 if size else low, interior + 1))
    out[tuple(target)] = operand
    return out


def _cholesky(a):
    """Lower Cholesky factor by the textbook recurrence on entries (zeros above the diagonal)."""
    n = a.shape[0]
    low = np.empty((n, n), dtype=object)
    low[...] = 0.0
    for j in range(n):
        low[j, j] = jnp.sqrt(a[j, j] - _sum([low[j, k] * low[j, k] for k in range(j)] or [0.0]))
        for i in range(j + 1, n):
            low[i, j] = (a[i, j] - _sum([low[i, k] * low[j, k] for k in range(j)] or [0.0])) / low[j, j]
    return low


def _triangular_solve(a, b, left_side, lower, transpose_a, unit_diagonal, **_):
    """``op(a) x = b`` (``left_side``) or ``x op(a) = b`` by substitution on entries."""
    if a.ndim != 2 or b.ndim != 2:
        raise NotImplementedError("batched triangular_solve")
    matrix, is_lower = (a.T, not lower) if transpose_a else (a, lower)
    if not left_side:  # x A = b  <=>  Aᵀ xᵀ = bᵀ
        return _triangular_solve(matrix.T, b.T, True, not is_lower, False, unit_diagonal).T
    n, k = b.shape
    x = np.empty((n, k), dtype=object)
    order = range(n) if is_lower else range(n - 1, -1, -1)
    for col in range(k):
        for i in order:
            known = range(i) if is_lower else range(i + 1, n)
            value = b[i, col] - _sum([matrix[i, j] * x[j, col] for j in known] or [0.0])
            x[i, col] = value if unit_diagonal else value / matrix[i, i]
    return x


def _slice(params, x):
    strides = params["strides"] or (1,) * x.ndim
    starts, limits = params["start_indices"], params["limit_indices"]
    return x[tuple(slice(a, b, s) for a, b, s in zip(starts, limits, strides))]


def _broadcast_in_dim(params, x):
    shape, dims = params["shape"], params["broadcast_dimensions"]
    expanded = np.reshape(x, [x.shape[dims.index(d)] if d in dims else 1 for d in range(len(shape))])
    return np.array(np.broadcast_to(expanded, shape))


def _iota(params):
    shape, dimension = params["shape"], params["dimension"]
    values = np.arange(shape[dimension], dtype=params["dtype"])
    values = values.reshape([-1 if d == dimension else 1 for d in range(len(shape))])
    return constant(np.broadcast_to(values, shape))


def _cumulative(combine):
    """A cumulative reduction (``cumsum``, ...) along ``params["axis"]`` with ``combine``."""

    def rule(params, x):
        axis, out = params["axis"], np.array(x, dtype=object)
        moved = np.moveaxis(out, axis, 0)  # a view: writing it fills ``out``
        reverse = params.get("reverse")
        order = range(moved.shape[0] - 2, -1, -1) if reverse else range(1, moved.shape[0])
        for i in order:
            previous = i + 1 if reverse else i - 1
            for index in np.ndindex(*moved.shape[1:]):
                moved[(i,) + index] = combine(moved[(previous,) + index], moved[(i,) + index])
        return out

    return rule


def _unbatched_cholesky(params, x):
    if x.ndim != 2:
        raise NotImplementedError("batched cholesky")
    return _cholesky(x)


# Structural primitives: bookkeeping on the object arrays (``rule(params, *operands)``), and the
# reductions and factorizations written out on entries.
_STRUCTURAL = {
    "slice": _slice,
    "squeeze": lambda params, x: np.squeeze(x, axis=tuple(params["dimensions"])),
    "expand_dims": lambda params, x: np.expand_dims(x, params["dimensions"]),
    "reshape": lambda params, x: np.reshape(x, params["new_sizes"]),
    "broadcast_in_dim": _broadcast_in_dim,
    "transpose": lambda params, x: np.transpose(x, params["permutation"]),
    "concatenate": lambda params, *xs: np.concatenate(xs, axis=params["dimension"]),
    "stack": lambda params, *xs: np.stack(xs, axis=params.get("axis", 0)),
    "unstack": lambda params, x: [np.array(part) for part in np.moveaxis(x, params.get("axis", 0), 0)],
    "split": lambda params, x: list(np.split(x, np.cumsum(params["sizes"])[:-1], axis=params["axis"])),
    "rev": lambda params, x: np.flip(x, axis=tuple(params["dimensions"])),
    "pad": lambda params, x, value: _pad(x, value, params["padding_config"]),
    "iota": _iota,
    "dot_general": lambda params, lhs, rhs: _dot_general(lhs, rhs, **params),
    "cumsum": _cumulative(operator.add),
    "cumprod": _cumulative(operator.mul),
    "cummax": _cumulative(jnp.maximum),
    "cummin": _cumulative(jnp.minimum),
    "cholesky": _unbatched_cholesky,
    "triangular_solve": lambda params, a, b: _triangular_solve(a, b, **params),
    "reduce_sum": lambda params, x: _reduce(operator.add, x, tuple(params["axes"])),
    "reduce_max": lambda params, x: _reduce(jnp.maximum, x, tuple(params["axes"])),
    "reduce_min": lambda params, x: _reduce(jnp.minimum, x, tuple(params["axes"])),
}


def evaluate(jaxpr: jcore.Jaxpr, consts, *args):
    """Evaluate ``jaxpr`` on object arrays of columns (see the module docstring)."""
    env = {}

    def read(v):
        if isinstance(v, jcore.Literal):
            return constant(v.val)
        return env[v]

    for var, value in zip(jaxpr.constvars, consts):
        env[var] = constant(value) if not isinstance(value, np.ndarray) or value.dtype != object else value
    for var, value in zip(jaxpr.invars, args):
        env[var] = value
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        operands = [read(v) for v in eqn.invars]
        inner = eqn.params.get("jaxpr", eqn.params.get("call_jaxpr", eqn.params.get("fun_jaxpr")))
        if name in _ELEMENTWISE:
            outs = [_elementwise(eqn.primitive, eqn.params, *operands)]
        elif name == "device_put":  # a host value placed while tracing: the values themselves
            outs = list(operands)
        elif name in _STRUCTURAL:
            result = _STRUCTURAL[name](eqn.params, *operands)
            outs = result if isinstance(result, list) else [result]
        elif inner is not None and name in (
            "pjit",
            "jit",
            "closed_call",
            "core_call",
            "custom_jvp_call",
            "custom_vjp_call",
            "remat",
            "checkpoint",
            "custom_vjp_call_jaxpr",
        ):
            closed = inner if hasattr(inner, "consts") else jcore.ClosedJaxpr(inner, ())
            outs = evaluate(closed.jaxpr, closed.consts, *operands)
        else:
            raise NotImplementedError(f"lane-wise evaluation of the primitive {name!r}")
        for var, value in zip(eqn.outvars, outs):
            if not isinstance(var, jcore.DropVar):
                env[var] = value
    return [read(v) for v in jaxpr.outvars]


def lanewise(fn, *example_args):
    """``fn`` (per member, on ``example_args``' shapes) as a function of object arrays of columns.

    Traces ``fn`` once; raises `NotImplementedError` at that point already if a primitive
    has no lane-wise rule (checked by a dry evaluation on scalar stand-ins).
    """
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*example_args)
    out_tree = jax.tree.structure(out_shape)

    def run(*object_args):
        flat = jax.tree.leaves(object_args, is_leaf=lambda x: isinstance(x, np.ndarray))
        outs = evaluate(closed.jaxpr, closed.consts, *flat)
        return jax.tree.unflatten(out_tree, outs)

    return run
