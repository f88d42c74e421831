"""Relightable environment mattes of rough glass, relighting and refractive flow (issue #27).

- :mod:`.record`: every environment lookup of a render and its weight in the image.
- :mod:`.matte`: the per-pixel lobes (:class:`Matte`), as passes and back.
- :mod:`.relight`: :func:`relight`, the image of a matte under any map, rotation, scale.
- :mod:`.flow`: refractive flow (TOM-Net, Chen et al. 2018) on a background plane.
- :mod:`.passes`: the ``passes`` a scene asks for, checked.
- :mod:`.render_hook`: what :func:`torchrefract.render` does for those passes.

See docs/matte.md. The submodules are imported on first use (the lighting code imports
:mod:`.record` at start-up and must not pull in the rest).
"""

from __future__ import annotations

import importlib

_EXPORTS = {"Matte": "matte", "PLAIN": "matte", "DEFAULT_LOBES": "matte",
            "from_passes": "matte", "to_passes": "matte", "relight": "relight",
            "parse_passes": "passes", "plane_flow": "flow"}


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"torchrefract.matte.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'torchrefract.matte' has no attribute {name!r}")


__all__ = sorted(_EXPORTS)
