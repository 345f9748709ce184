"""Shared plumbing of the ready-made models: parameters with defaults, form checks."""

from __future__ import annotations

import functools
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, Callable, Protocol

from .._system import System


class Model(Protocol):
    """A model factory decorated by :func:`model`: returns a :class:`System` and carries its
    default parameters."""

    defaults: Mapping[str, Any]
    allow_extra: bool

    def __call__(self, *args: Any, **kwargs: Any) -> System: ...


def model(defaults: dict, *, allow_extra: bool = False) -> Callable:
    """Decorate a model factory: record its default parameters as ``factory.defaults`` and
    memoize it, so that asking twice for the same model returns the same :class:`System` (whose
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
        unknown = sorted(set(args) - set(defaults))
        if unknown:
            raise KeyError(
                f"jaxlag.systems.{factory.__name__}: unknown parameter(s) {unknown}; its "
                f"parameters are {sorted(defaults)}."
            )
    return {**defaults, **args}


def check_form(name: str, form: str, allowed: tuple[str, ...]) -> str:
    if form not in allowed:
        raise ValueError(f"jaxlag.systems.{name}: form must be one of {allowed}; got {form!r}.")
    return form


def default_args(factory: Model) -> dict:
    """A fresh dict of a model's default parameters (edit it and pass it as ``args``)."""
    if not hasattr(factory, "defaults"):
        raise TypeError(f"{factory!r} is not a jaxlag.systems model.")
    return dict(factory.defaults)
