"""Method options: each one a dataclass field carrying its default, its check and its
docstring; one parser for every method, the sweep and the CLI.

A method's ``Options`` is a frozen dataclass whose fields are declared with :func:`option`
(a number with its range, a choice, a boolean, or a custom check). :func:`parse_options`
turns a ``method_options`` mapping into it: unknown keys, wrong types and out-of-range values
raise :class:`~torchrefract.checks.ConfigError` naming the file, ``method_options.KEY`` and the
value. A field whose type is itself an options dataclass (``bounces``) reads its fields from
the same flat mapping, so ``internal_bounces: 2`` sits beside ``tir: clamp``.

Example:
    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class Opts:
    ...     steps: int = option(8, minimum=1, integer=True)
    >>> parse_options(Opts, {"steps": 4}, "demo").steps
    4
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Sequence

from torchrefract.checks import (
    ConfigError,
    check_bool,
    check_choice,
    check_file,
    check_number,
    check_option_keys,
    where,
)

Check = Callable[[Any, str, "str | None"], Any]
"""check(value, key, source) -> the value to store, or a ConfigError."""


def option(default: Any, *, choices: Sequence[Any] | None = None,
           minimum: float | None = None, maximum: float | None = None,
           integer: bool = False, boolean: bool = False, path: bool = False,
           check: Check | None = None) -> Any:
    """A dataclass field with its default and its check (one of: ``choices``, a number with
    ``minimum`` / ``maximum`` / ``integer``, ``boolean``, ``path`` (a file, relative to the
    scene file) or a custom ``check``)."""
    return dataclasses.field(default=default, metadata={"option": {
        "choices": choices, "minimum": minimum, "maximum": maximum, "integer": integer,
        "boolean": boolean, "path": path, "check": check}})


def nested(cls: type) -> Any:
    """A field holding another options dataclass whose keys sit in the same mapping."""
    return dataclasses.field(default=cls(), metadata={"nested": cls})


def option_keys(cls: type) -> list[str]:
    """Every key ``cls`` accepts, nested fields flattened, in declaration order."""
    keys: list[str] = []
    for f in dataclasses.fields(cls):
        if "nested" in f.metadata:
            keys += option_keys(f.metadata["nested"])
        else:
            keys.append(f.name)
    return keys


def _check_one(spec: dict, value: Any, key: str, source: str | None) -> Any:
    if spec["check"] is not None:
        return spec["check"](value, key, source)
    if spec["boolean"]:
        return check_bool(value, key, source)
    if spec["path"]:
        if value is None:
            return None
        base = Path(source).parent if source and Path(source).is_file() else Path.cwd()
        return check_file(value, key, base, source)
    if spec["choices"] is not None:
        if all(isinstance(c, str) for c in spec["choices"]):
            return check_choice(value, key, spec["choices"], source)
        if isinstance(value, bool) or value not in spec["choices"]:
            wanted = " or ".join(repr(c) for c in spec["choices"])
            raise ConfigError(f"{where(source, key)}: expected {wanted}, got {value!r}")
        return type(spec["choices"][0])(value)
    return check_number(value, key, source, minimum=spec["minimum"], maximum=spec["maximum"],
                        integer=spec["integer"])


def _build(cls: type, d: dict, source: str | None) -> Any:
    values = {}
    for f in dataclasses.fields(cls):
        if "nested" in f.metadata:
            values[f.name] = _build(f.metadata["nested"], d, source)
        elif f.name in d:
            values[f.name] = _check_one(f.metadata["option"], d[f.name],
                                        f"method_options.{f.name}", source)
    return cls(**values)


def parse_options(cls: type, d: dict | None, source: str | None = None,
                  method: str | None = None, exclude: Sequence[str] = ()) -> Any:
    """``method_options`` as an instance of ``cls`` (defaults for the keys not given).

    Args:
        cls: the method's options dataclass (fields made with :func:`option`, :func:`nested`).
        d: the mapping (None: all defaults).
        source: the scene file (or a description) for error messages.
        method: the method's name for the unknown-key message.
        exclude: keys of nested fields this method does not accept.

    Raises:
        ConfigError: an unknown key, or a value of the wrong type or out of range.
    """
    d = {} if d is None else d
    if not isinstance(d, dict):
        raise ConfigError(f"{where(source, 'method_options')}: expected a mapping, got {d!r}")
    allowed = [k for k in option_keys(cls) if k not in exclude]
    check_option_keys(d, allowed, method or cls.__name__, source)
    return _build(cls, d, source)


def options_dict(opts: Any) -> dict:
    """The flat ``method_options`` mapping of an options instance (every key, nested ones
    flattened): what :func:`parse_options` turns back into the same instance."""
    out: dict = {}
    for f in dataclasses.fields(opts):
        v = getattr(opts, f.name)
        if "nested" in f.metadata:
            out.update(options_dict(v))
        else:
            out[f.name] = v
    return out


__all__ = ["nested", "option", "option_keys", "options_dict", "parse_options"]
