"""Methods by name, imported only when used.

Built-in methods are listed here by module path (so that the scene loader can check a
name without importing any renderer); third-party ones come from the Python entry-point
group ``torchrefract.methods`` (``name = "package.module:OBJECT"``) or from
:func:`register_method`, and then work from YAML, the CLI, sweeps and ``render()`` alike.
``auto`` is a policy, not a method: it picks methods per scene (:mod:`torchrefract.auto`).
"""

from __future__ import annotations

import importlib
import sys
import warnings
from importlib import metadata
from typing import Any

from torchrefract.checks import ConfigError

ENTRY_POINT_GROUP = "torchrefract.methods"

_BUILTIN = {
    "specular": "torchrefract.methods.specular:METHOD",
    "prefiltered": "torchrefract.methods.prefiltered:METHOD",
    "rousiers": "torchrefract.methods.rousiers:METHOD",
    "lean": "torchrefract.methods.lean:LEAN",
    "gsr": "torchrefract.methods.lean:GSR",
    "sh": "torchrefract.methods.sh:METHOD",
    "reference": "torchrefract.methods.reference:METHOD",
}
POLICIES = {"auto": "torchrefract.auto:POLICY"}
"""Names a scene may ask for that choose other methods instead of shading."""

_registered: dict[str, Any] = {}
_loaded: dict[str, Any] = {}


def register_method(name: str, method: Any) -> None:
    """Make ``method`` (a :class:`~torchrefract.methods.base.Method`, its class, or a
    ``"module:object"`` path) available as ``name`` everywhere a method is named."""
    if not isinstance(name, str) or not name.isidentifier():
        raise ConfigError(f"register_method: expected a method name (an identifier), "
                          f"got {name!r}")
    if name in POLICIES:
        raise ConfigError(f"register_method: {name!r} is a policy, not a method name")
    if isinstance(method, str):
        module, colon, attr = method.partition(":")
        if not (colon and module and attr.isidentifier()):
            raise ConfigError(f"register_method({name!r}): expected 'package.module:OBJECT', "
                              f"got {method!r}")
    elif not (isinstance(method, type) or callable(getattr(method, "shade", None))):
        raise ConfigError(f"register_method({name!r}): expected a Method, its class or a "
                          f"'module:OBJECT' path, got {method!r}")
    if name in _BUILTIN:
        warnings.warn(f"register_method: {name!r} replaces the built-in method of that name "
                      "for every scene that names it", stacklevel=2)
    _registered[name] = method
    _loaded.pop(name, None)


_EP_CACHE: dict[tuple[str, ...], dict[str, Any]] = {}


def _entry_points() -> dict[str, Any]:
    """The group's entry points, read once per ``sys.path`` (reading every installed
    distribution's metadata took ~4 ms, and every scene check names the methods)."""
    key = tuple(sys.path)
    hit = _EP_CACHE.get(key)
    if hit is not None:
        return hit
    try:
        eps = {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}
    except Exception:  # noqa: BLE001 (broken metadata of some other package)
        eps = {}
    _EP_CACHE.clear()
    _EP_CACHE[key] = eps
    return eps


def _sources() -> dict[str, Any]:
    out: dict[str, Any] = dict(_BUILTIN)
    out.update(_entry_points())
    out.update(_registered)
    return out


def method_names() -> tuple[str, ...]:
    """Every name a scene's ``method`` may take: the methods and the policies."""
    return tuple(_sources()) + tuple(POLICIES)


def _resolve(name: str, source: Any) -> Any:
    try:  # a plug-in that cannot be loaded or made fails naming the method
        if isinstance(source, metadata.EntryPoint):
            obj = source.load()
        elif isinstance(source, str):
            module, _, attr = source.partition(":")
            obj = getattr(importlib.import_module(module), attr)
        else:
            obj = source
        if isinstance(obj, type):
            obj = obj()
    except (ImportError, AttributeError, TypeError) as exc:
        raise ConfigError(f"method {name!r}: cannot load {source!r}: "
                          f"{type(exc).__name__}: {exc}") from None
    for attr in ("parse", "prepare", "shade") if name not in POLICIES else ("parse", "resolve"):
        if not callable(getattr(obj, attr, None)):
            raise ConfigError(f"method {name!r}: {obj!r} has no {attr}() (see "
                              "torchrefract.methods.base.Method)")
    return obj


def get(name: str) -> Any:
    """The method (or policy) called ``name``.

    Raises:
        ConfigError: an unknown name (the known ones listed).
    """
    hit = _loaded.get(name)
    if hit is not None:
        return hit
    sources = _sources()
    if name in POLICIES:
        src = POLICIES[name]
    elif name in sources:
        src = sources[name]
    else:
        raise ConfigError(f"unknown method {name!r} (available: {sorted(method_names())})")
    obj = _resolve(name, src)
    _loaded[name] = obj
    return obj


def is_policy(name: str) -> bool:
    return name in POLICIES


__all__ = ["ENTRY_POINT_GROUP", "POLICIES", "get", "is_policy", "method_names",
           "register_method"]
