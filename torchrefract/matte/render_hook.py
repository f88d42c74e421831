"""What :func:`torchrefract.render` does for the ``matte`` and ``flow`` passes: check the
method, render through the tensor code with the lookups recorded, and turn the recording
into pixel passes (:mod:`.matte`, :mod:`.flow`)."""

from __future__ import annotations

from contextlib import contextmanager, nullcontext
from typing import Iterator

import torch

from torchrefract.checks import ConfigError

MATTE_METHODS = ("specular", "prefiltered", "rousiers", "lean", "gsr", "sh")
"""Methods whose mattes are tested (tests/test_matte.py): every lookup of their tensor code
goes through :mod:`torchrefract.lighting.lights`. ``lean``/``gsr`` need ``env_lookup: sg``
(a box MIP lookup is not an SG lobe)."""


def requested(scenes) -> dict:
    """The batch's ``passes`` (checked equal across the batch by the renderer)."""
    return dict(scenes[0].passes) if scenes else {}


def check(method: str, passes: dict, options=None) -> None:
    """ConfigError where ``method`` cannot give the requested passes."""
    if not passes:
        return
    names = ", ".join(sorted(passes))
    if method not in MATTE_METHODS:
        raise ConfigError(f"passes ({names}): method {method!r} has no environment matte; "
                          f"use one of {', '.join(MATTE_METHODS)}")
    if getattr(options, "env_lookup", "sg") != "sg":
        raise ConfigError(f"passes ({names}): method {method!r} with "
                          f"method_options.env_lookup: {options.env_lookup} reads a box MIP, "
                          "not an SG lobe; use env_lookup: sg")


@contextmanager
def settings_for(passes: dict) -> Iterator[None]:
    """The render's settings with the tensor code (no fused kernel: it records nothing) and
    uniform supersampling (adaptive sampling lets one sample stand for several sub-pixels)."""
    if not passes:
        yield
        return
    from torchrefract.settings import current, using  # noqa: PLC0415

    s = current()
    if not s.fused and not s.adaptive:
        yield
        return
    with using(s.replace(fused=False, adaptive=False)):
        yield


def scope(passes: dict):
    """A recording of the lookups where passes are asked for, else nothing."""
    if not passes:
        return nullcontext(None)
    from torchrefract.matte.record import recording  # noqa: PLC0415

    return recording()


def make_passes(rec, radiance_sub: torch.Tensor, box, g, scenes, passes: dict
                ) -> dict[str, torch.Tensor]:
    """The requested passes (B, H, W, C) from a recording and the sub-pixel image (with
    its graph); ``box`` is the renderer's box filter (x, n) -> pixels."""
    from torchrefract.matte import matte as mm  # noqa: PLC0415
    from torchrefract.matte.flow import plane_flow  # noqa: PLC0415
    from torchrefract.matte.record import weights  # noqa: PLC0415

    b, hs, ws, _ = radiance_sub.shape
    n = g.supersample
    shape = (b, hs // n, ws // n)
    entries = weights(rec, radiance_sub)
    out: dict[str, torch.Tensor] = {}
    if "matte" in passes:
        img = box(radiance_sub.detach(), n)
        has_lights = torch.tensor([len(s.lights) > 0 for s in scenes])
        m = mm.build(entries, img, shape, n, int(passes["matte"]["lobes"]), has_lights)
        out.update(mm.to_passes(m))
    if "flow" in passes:
        out.update(plane_flow(entries, g, [s.camera for s in scenes],
                              float(passes["flow"]["distance"]), shape))
    rec.lookups.clear()
    return out


__all__ = ["MATTE_METHODS", "check", "make_passes", "requested", "scope", "settings_for"]
