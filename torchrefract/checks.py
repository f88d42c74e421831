"""Validation of user input: one place, clear messages naming the field and the value.

Every check raises :class:`ConfigError` (a ``ValueError``) whose message names where the
value came from (file and key path), what was expected and what was found. Never use a bare
``assert`` on user input (kornia's ``KORNIA_CHECK`` style).
"""

from __future__ import annotations

import functools
import math
import os
from numbers import Real
from pathlib import Path
from typing import Any, Sequence


class ConfigError(ValueError):
    """A scene, config or asset that cannot be rendered as given."""


RADIANCE_LIMIT = 1e15
"""Largest environment texel, ``envmap.scale`` and light radiance accepted (a sun in an HDR
map is ~1e5-1e6): their product stays within float32 with room for the shading's weights
and the box filter's sums, so radiance stays finite."""


def where(source: str | None, key: str) -> str:
    """Format a location as ``file: key`` (or just ``key``)."""
    return f"{source}: {key}" if source else key


def check_number(value: Any, key: str, source: str | None = None, *,
                 minimum: float | None = None, maximum: float | None = None,
                 min_inclusive: bool = True, integer: bool = False) -> float:
    """Return ``value`` as float (or int) after checking type, finiteness and range."""
    loc = where(source, key)
    if isinstance(value, bool) or not isinstance(value, Real):
        kind = "an integer" if integer else "a number"
        hint = ""
        if isinstance(value, str):
            try:
                float(value)
                hint = " (YAML reads 1e-3 as text: write 1.0e-3)"
            except ValueError:
                pass
        raise ConfigError(f"{loc}: expected {kind}, got {value!r} ({type(value).__name__})"
                          f"{hint}")
    v = float(value)
    if not math.isfinite(v):  # before int(): NaN and infinity have no integer
        raise ConfigError(f"{loc}: expected a finite number, got {value!r}")
    if integer and int(value) != value:
        raise ConfigError(f"{loc}: expected an integer, got {value!r}")
    if minimum is not None:
        if min_inclusive and v < minimum:
            raise ConfigError(f"{loc}: must be >= {minimum}, got {value!r}")
        if not min_inclusive and v <= minimum:
            raise ConfigError(f"{loc}: must be > {minimum}, got {value!r}")
    if maximum is not None and v > maximum:
        limit = f"{maximum:g}" if abs(maximum) >= 1e6 else f"{maximum}"
        raise ConfigError(f"{loc}: must be <= {limit}, got {value!r}")
    return int(value) if integer else v


def check_vector(value: Any, key: str, source: str | None = None, *, length: int = 3,
                 minimum: float | None = None,
                 maximum: float | None = None) -> tuple[float, ...]:
    """Return a tuple of ``length`` finite floats."""
    loc = where(source, key)
    if not isinstance(value, Sequence) or isinstance(value, (str, bytes)):
        raise ConfigError(f"{loc}: expected a list of {length} numbers, got {value!r}")
    if len(value) != length:
        raise ConfigError(f"{loc}: expected {length} numbers, got {len(value)}: {value!r}")
    return tuple(check_number(v, f"{key}[{i}]", source, minimum=minimum, maximum=maximum)
                 for i, v in enumerate(value))


def check_bool(value: Any, key: str, source: str | None = None) -> bool:
    """Return ``value`` if it is a boolean (YAML ``true`` / ``false``)."""
    if not isinstance(value, bool):
        raise ConfigError(f"{where(source, key)}: expected true or false, got {value!r}")
    return value


def check_choice(value: Any, key: str, choices: Sequence[str], source: str | None = None) -> str:
    loc = where(source, key)
    if not isinstance(value, str) or value not in choices:
        raise ConfigError(f"{loc}: expected one of {list(choices)}, got {value!r}")
    return value


def check_keys(mapping: Any, key: str, allowed: Sequence[str], source: str | None = None,
               required: Sequence[str] = ()) -> dict:
    """Check that ``mapping`` is a dict with only ``allowed`` keys and all ``required`` ones."""
    loc = where(source, key or "<top level>")
    if not isinstance(mapping, dict):
        raise ConfigError(f"{loc}: expected a mapping, got {mapping!r} ({type(mapping).__name__})")
    unknown = [k for k in mapping if k not in allowed]
    if unknown:
        raise ConfigError(f"{loc}: unknown key {unknown[0]!r} (allowed: {sorted(allowed)})")
    missing = [k for k in required if k not in mapping]
    if missing:
        raise ConfigError(f"{loc}: missing required key {missing[0]!r}")
    return mapping


def check_tensor_shape(t, shape: Sequence[int | None], name: str) -> None:
    """Check a tensor's shape; ``None`` entries match any size (kornia ``KORNIA_CHECK_SHAPE``)."""
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ConfigError(f"{name}: expected shape {want}, got {tuple(t.shape)}")


def check_file(value: Any, key: str, base_dir: Path, source: str | None = None) -> str:
    """Resolve a file path (a string or ``os.PathLike``, relative to ``base_dir``) and check
    that the file exists."""
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where(source, key)}: expected a file path, got {value!r}")
    p = Path(value).expanduser()
    if not p.is_absolute():
        p = Path(base_dir) / p
    if not p.is_file():
        raise ConfigError(f"{where(source, key)}: file not found: {value!r} (looked at {p})")
    return str(p.resolve())


def check_option_keys(options: dict, allowed: Sequence[str], method: str,
                      source: str | None = None) -> None:
    """Reject ``method_options`` keys a method does not know, naming the key and the method."""
    for k in options:
        if k not in allowed:
            raise ConfigError(f"{source + ': ' if source else ''}method_options: unknown key "
                              f"{k!r} for method {method!r} (allowed: {list(allowed)})")


def load_yaml_file(path: str | Path, what: str) -> Any:
    """Parse a YAML file with ``yaml.safe_load``; missing, invalid or empty is a ConfigError."""
    import yaml  # noqa: PLC0415

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{what} file not found: {str(path)!r}")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        data = yaml.load(text, Loader=_loader())  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML: {exc}") from None
    except _DuplicateKey as exc:
        raise ConfigError(f"{p}: {exc}") from None
    if data is None:
        raise ConfigError(f"{p}: the file is empty")
    return data


class _DuplicateKey(Exception):
    """A mapping names one key twice (YAML itself lets the last win, silently)."""


@functools.lru_cache(maxsize=1)
def _loader():
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping."""
    import yaml  # noqa: PLC0415

    class Loader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=deep)
                if isinstance(key, str) and key in seen:
                    raise _DuplicateKey(f"key {key!r} given twice (line "
                                        f"{key_node.start_mark.line + 1})")
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    return Loader


def file_version(path: str | Path, what: str) -> tuple[str, int, int]:
    """(resolved path, mtime in ns, size) of an existing file: the key of the per-file caches,
    so a file rewritten in place is read again. Missing file: ConfigError naming ``what``."""
    name = os.fspath(path)
    try:
        st = os.stat(name)  # (not a Path object: this runs for every file of every render)
    except (OSError, ValueError):
        raise ConfigError(f"{what} {str(path)!r}: file not found") from None
    return _resolved(name), st.st_mtime_ns, st.st_size


@functools.lru_cache(maxsize=1024)
def _resolved(path: str) -> str:
    """``Path.resolve`` of a path, kept: a render checks each scene's files' versions, and
    resolving (a ``lstat`` per path component) cost more than the check."""
    return str(Path(path).resolve())
