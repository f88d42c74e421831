"""Fused shading of ``lean`` and ``gsr`` (kernels/csrc/lean.c): the one place where those
methods choose between the fused kernel and their tensor code (methods/lean/shade.py).

The LEAN moments' mip pyramid is built by the tensor code (``moments.lean_mips``); the
kernel does the per-pixel work after it: the front lobes and the marched cone
(``rousiers``' steps, the same C functions), the footprint's moments and Gaussians, the
exit lobes placed by the bounding rays (``spread: rays``), ``gsr``'s subdivision lobes where
the normals part, the EWA taps on the SG pyramid, the front reflection and ``rousiers``'
finish (index-matched objects, lights, absorption, internal bounces).

It runs where :mod:`.fused`'s kernels run (the native kernels are built, the settings ask
for it, no input wants a gradient, CPU float32) and the options are covered: ``spread:
rays``, ``env_lookup: sg``, at most 64 sphere lights; any ``tir``, ``cone_rays``,
``ewa_taps``, ``roughness_lobes``, subdivisions (1-8), roughness maps and internal bounces.
Elsewhere :func:`lean` returns ``None`` and the tensor code runs; tests/test_fused_lean.py
holds the two to the same images.
"""

from __future__ import annotations

import ctypes
import threading
import warnings

import torch

from torchrefract.kernels import native
from torchrefract.methods.rousiers.options import DIFFUSE_VAR
from torchrefract.shading import fused

_p = ctypes.c_void_p


class _LeanJob(ctypes.Structure):
    """ctypes mirror of ``LeanJob`` in csrc/lean.c."""

    _fields_ = [("r", native._RousJob), ("k", ctypes.c_int), ("lobes", ctypes.c_int),
                ("taps", ctypes.c_int), ("mips", ctypes.c_int), ("texel", ctypes.c_int),
                ("lean", _p), ("lean_hw", _p)]


class _MomentsJob(ctypes.Structure):
    """ctypes mirror of ``MomentsJob`` in csrc/lean.c."""

    _fields_ = [("f", native._Frame), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("k", ctypes.c_int), ("compact", ctypes.c_int), ("normal", _p), ("uv", _p),
                ("mask", _p), ("out", _p)]


_LOCK = threading.Lock()
_READY: bool | None = None


def _ready() -> bool:
    """Whether the loaded library has the kernel with this module's job layout (checked
    once; a mismatch warns and leaves the tensor code to run)."""
    global _READY
    if _READY is None:
        with _LOCK:
            if _READY is None:
                try:
                    native.bind(native._LIB, {"lean": _LeanJob, "lean_moments": _MomentsJob})
                    ok = True
                except (AttributeError, RuntimeError):  # missing, or another layout
                    ok = False
                if not ok:
                    warnings.warn("torchrefract: the native library's lean kernel is missing "
                                  "or its job layout differs from fused_lean.py's; lean and "
                                  "gsr run their tensor code", RuntimeWarning, stacklevel=3)
                _READY = ok
    return _READY


def covered(options, lighting, spread: str) -> bool:
    """Whether the kernel covers these options (module docstring)."""
    return (spread == "rays" and options.env_lookup == "sg"
            and lighting.light_pos.shape[1] <= 64)


def lean(g, lighting, materials, options, radiance: torch.Tensor, subdivisions: int = 1,
         spread: str = "rays") -> tuple[torch.Tensor, dict] | None:
    """``render_lean``'s radiance (B, H, W, 3) and passes (``exit_found``, ``tir``,
    ``lobe_sigma``, ``footprint``; with internal bounces ``bounces``, ``bounce_residual``),
    shaded over ``radiance`` (B*H*W, 3), the background (written in place); ``None``, and
    ``radiance`` untouched, where the fused kernel does not run (module docstring)."""
    from torchrefract.methods.lean.moments import reads_no_moments  # (as in _mips)

    if not covered(options, lighting, spread) or not 1 <= subdivisions <= 8:
        return None
    made = fused._frame(g, lighting, materials, options, radiance, sg_env=True)
    if made is None or not _ready():
        return None
    frame, keep, radiance, passes = made
    b, h, w = g.shape
    rous = fused.rous_job(g, options, frame, keep, passes, DIFFUSE_VAR)
    if frame.n == 0:
        return radiance.view(b, h, w, 3), passes
    lobes = options.roughness_lobes if materials.has_maps else 1
    mips, texel = (((), 0) if reads_no_moments(subdivisions, spread, materials.has_maps)
                   else _mips(g, materials, subdivisions, lobes))
    job = _LeanJob(
        r=rous, k=subdivisions, lobes=lobes, taps=options.ewa_taps, mips=len(mips), texel=texel,
        lean=keep.array(mips),
        lean_hw=keep.ptr(torch.tensor([m.shape[1:3] for m in mips]), torch.int64))
    if not fused._run("lean", job, g, radiance, passes):
        return None
    return radiance.view(b, h, w, 3), passes


def moments(g, materials, k: int, compact: int = 0) -> torch.Tensor | None:
    """``moments.lean_mips``' level 0, the back layer's LEAN moments (B, H, W, K * CHANNELS),
    by the kernel; ``None`` where it does not run (not built, or an input wants a
    gradient). ``compact`` 2 or 4 (K = 1): only the channels ``lean``'s merged Gaussian
    reads, w and w u (and w u^2, w u^3 for two roughness lobes), (B, H, W, compact);
    ``SLOPE_CHANNELS``: each subdivision's without the roughness's, (B, H, W, K * 6)."""
    from torchrefract.methods.lean.moments import CHANNELS, SLOPE_CHANNELS as SLOPE  # (_mips)

    b, h, w = g.shape
    maps = list(materials.roughness_maps) or [None] * b
    if not (native.available() and _ready() and g.back.normal.device.type == "cpu"
            and native.no_grad_through(g.back.normal, g.back.uv, materials.roughness,
                                       *[m for m in maps if m is not None])):
        return None
    keep = fused._Keep()
    frame = native._Frame(
        nb=b, basis=keep.ptr(g.proj[:, 3:12]), alpha=keep.ptr(materials.roughness),
        rmap=keep.array(maps),
        rmap_hw=keep.ptr(torch.tensor([(1, 1) if m is None else m.shape for m in maps]),
                         torch.int64),
        rrange=keep.ptr(materials.roughness_range if materials.roughness_range is not None
                        else torch.zeros(b, 2)))
    out = torch.empty(b, h, w, k * SLOPE if compact == SLOPE else compact or k * CHANNELS)
    job = _MomentsJob(f=frame, h=h, w=w, k=k, compact=compact, normal=keep.ptr(g.back.normal),
                      uv=keep.ptr(g.back.uv), mask=keep.ptr(g.back.mask, torch.bool),
                      out=out.data_ptr())
    return out if native._call("lean_moments", job) else None


def _mips(g, materials, k: int, lobes: int) -> tuple[tuple[torch.Tensor, ...], int]:
    """``moments.lean_mips`` and its channels per texel: level 0 by the kernel where it runs
    (for ``lean`` only the channels it reads: with spread ``rays`` the merged Gaussian's
    mean and covariance are not used, and a pyramid of 2 channels instead of 9 stays in
    cache), the box mips by torch."""
    # (imported here: the methods import this module)
    from torchrefract.methods.lean.moments import SLOPE_CHANNELS as SLOPE, lean_mips
    from torchrefract.optics.ndf import build_box_mips

    # ``gsr`` with one roughness per view: no roughness channels (footprint_sums)
    compact = (4 if lobes == 2 else 2) if k == 1 else (0 if materials.has_maps else SLOPE)
    level0 = moments(g, materials, k, compact)
    mips = (lean_mips(g, materials, k, materials.has_maps) if level0 is None
            else build_box_mips(level0))
    return mips, mips[0].shape[-1]


__all__ = ["covered", "lean", "moments"]
