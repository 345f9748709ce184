"""Shared plumbing of the ready-made models: parameters with defaults, form checks."""

import difflib
import functools
from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import Any, Protocol, runtime_checkable

from .._custom_types import Validated
from .._system import System
from ..robots._tree import KinematicTree


@runtime_checkable
class Model(Protocol):
    """A model factory decorated by `model`: returns a `System` and carries its
    default parameters."""

    defaults: Mapping[str, Any]
    allow_extra: bool

    def __call__(self, *args: Any, **kwargs: Any) -> System: ...


def model(defaults: dict, *, allow_extra: bool = False) -> Callable:
    """Decorate a model factory: record its default parameters as ``factory.defaults`` and
    memoize it, so that asking twice for the same model returns the same `System` (whose
    compiled simulations are then reused instead of recompiled)."""

    def wrap(factory):
        cached: Any = functools.lru_cache(maxsize=None)(factory)  # carries two extra attributes
        cached.defaults = MappingProxyType(dict(defaults))
        cached.allow_extra = allow_extra
        return cached

    return wrap


def parameters(factory, args) -> dict:
    """``args`` merged over ``factory.defaults``; unknown names are an error (typos)."""
    defaults = factory.defaults
    if args is None:
        return dict(defaults)
    if not isinstance(args, Mapping):
        raise TypeError(
            f"jaxlag.systems.{factory.__name__} reads its parameters from a dict `args` with keys "
            f"{sorted(defaults)} (missing keys take their defaults); got {type(args).__name__}."
        )
    if not factory.allow_extra:
        check_keys(factory, args)
    return {**defaults, **args}


_WORDS = {"l": "length", "m": "mass", "g": "gravity", "R": "radius", "I": "inertia"}


class UnknownParameterError(KeyError):
    """A key of ``args`` that a ready model does not know (a ``KeyError`` whose message prints
    as written, not quoted)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class KeyReads(Mapping):
    """A read-only view of a dict that records which keys are read (``[k]``, ``get``, ``in``);
    iterating over it (``keys()``, ``items()``, ``{**args}``) counts as reading every key."""

    def __init__(self, data: Mapping):
        self._data = data
        self.read: set = set()
        self.everything = False

    def __getitem__(self, key):
        self.read.add(key)
        return self._data[key]

    def __contains__(self, key) -> bool:
        self.read.add(key)
        return key in self._data

    def __iter__(self):
        self.everything = True
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)


def check_keys(factory, args, read_elsewhere=(), reader: str = "") -> None:
    """Refuse the keys of ``args`` that are not parameters of the model (nor in
    ``read_elsewhere``, the keys that ``reader``, e.g. a controller, reads), naming for each
    the closest parameter: a misspelt key would otherwise leave its default silently in use."""
    known = set(factory.defaults)
    unknown = sorted(str(k) for k in set(args) - known - set(read_elsewhere))
    if not unknown:
        return
    # One-letter parameters are matched by what they stand for too ('lenght' -> 'l').
    spelled = {word: k for k, word in _WORDS.items() if k in known}
    close = []
    for key in unknown:
        match = difflib.get_close_matches(key, sorted(known) + sorted(spelled), n=1, cutoff=0.5) or [
            k for k in sorted(known) if k.lower() == key.lower()
        ]
        if match:
            close.append(f"{key!r} -> did you mean {spelled.get(match[0], match[0])!r}?")
    hint = f" ({'; '.join(close)})" if close else ""
    used = f" nor read by {reader}" if reader else ""
    raise UnknownParameterError(
        f"jaxlag.systems.{factory.__name__}: unknown parameter(s) {unknown}{hint}, not parameters "
        f"of the model{used}; its parameters are {sorted(known)} (missing ones take their "
        "defaults, so a misspelt key would leave the default in use)."
    )


def check_form(name: str, form: str, allowed: tuple[str, ...]) -> str:
    if form not in allowed:
        raise ValueError(f"jaxlag.systems.{name}: form must be one of {allowed}; got {form!r}.")
    return form


def default_args(factory: Validated[Model]) -> dict | KinematicTree:
    """A fresh dict of a model's default parameters (edit it and pass it as ``args``); for the
    robots (`robot_arm`, `space_robot`) their [`KinematicTree`][jaxlag.robots.KinematicTree]
    (immutable: edit it with ``equinox.tree_at``; loading it needs MuJoCo)."""
    if not hasattr(factory, "defaults"):
        raise TypeError(f"{factory!r} is not a jaxlag.systems model.")
    tree = getattr(factory, "tree", None)
    if tree is not None:
        return tree()
    return dict(factory.defaults)
