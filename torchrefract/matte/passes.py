"""The optional output passes a scene asks for (``passes`` in a scene or sweep base YAML,
``--passes`` on the CLI), checked and resolved with their defaults.

Forms accepted (all resolve to ``{name: {option: value}}``)::

    passes: [matte, flow]                       # names, default options
    passes: {matte: {lobes: 8}, flow: {distance: 2.0}}

- ``matte`` (:mod:`torchrefract.matte.matte`): ``lobes``, the lobe slots per pixel (1-64,
  default :data:`~torchrefract.matte.matte.DEFAULT_LOBES`).
- ``flow`` (:mod:`torchrefract.matte.flow`): ``distance``, the background plane's distance
  behind the camera's target along the view axis (world units, > 0, default 2.0).

Either pass renders through the methods' tensor code (``RenderSettings(fused=False,
adaptive=False)`` for that render), where every environment lookup is recorded.
"""

from __future__ import annotations

from typing import Any

from torchrefract.checks import ConfigError, check_keys, check_number, where
from torchrefract.matte.matte import DEFAULT_LOBES

PASS_OPTIONS: dict[str, dict[str, tuple]] = {
    "matte": {"lobes": (DEFAULT_LOBES, dict(minimum=1, maximum=64, integer=True))},
    "flow": {"distance": (2.0, dict(minimum=0.0, min_inclusive=False))},
}
"""name -> option -> (default, check_number keywords)."""


def parse_passes(value: Any, source: str | None = None, key: str = "passes"
                 ) -> dict[str, dict[str, Any]]:
    """``passes`` checked and resolved (module docstring).

    Raises:
        ConfigError: an unknown pass or option, or a bad value (file, key and value named).
    """
    if value is None:
        return {}
    if isinstance(value, str):
        value = [value]
    if isinstance(value, (list, tuple)):
        names = list(value)
        for i, n in enumerate(names):
            if not isinstance(n, str):
                raise ConfigError(f"{where(source, f'{key}[{i}]')}: expected a pass name "
                                  f"({', '.join(PASS_OPTIONS)}), got {n!r}")
        value = {n: {} for n in names}
    if not isinstance(value, dict):
        raise ConfigError(f"{where(source, key)}: expected a list of pass names or a mapping "
                          f"name -> options, got {value!r}")
    out: dict[str, dict[str, Any]] = {}
    for name, opts in value.items():
        if name not in PASS_OPTIONS:
            raise ConfigError(f"{where(source, key)}: unknown pass {name!r}; expected one of "
                              f"{', '.join(PASS_OPTIONS)}")
        opts = {} if opts is None else opts
        spec = PASS_OPTIONS[name]
        check_keys(opts, f"{key}.{name}", tuple(spec), source)
        out[name] = {k: check_number(opts.get(k, default), f"{key}.{name}.{k}", source, **kw)
                     for k, (default, kw) in spec.items()}
    return out


__all__ = ["PASS_OPTIONS", "parse_passes"]
