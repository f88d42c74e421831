"""Native kernels: the ray march's discrete part (``csrc/march.c``), the exact G-buffer
layer (``csrc/gbuffer.c``), the G-buffer's triangle ids (``csrc/raster.c``, in place of
the OpenGL passes: ``RenderSettings.rasterizer``) and the cone's footprint and spread
(``csrc/cone.c``), built on first use.

Where each marched ray crosses the back-face layer, and which triangle it leaves through,
is a discrete choice with no gradient (``march.py``). In tensor code it is a chain of
elementwise ops and gathers per sample over all rays, bound by memory traffic; the C
kernel makes the same choices one ray at a time, in the same float32 arithmetic. Where a
gradient is wanted, ``march.py`` then intersects each ray with its chosen triangle in
torch; elsewhere the kernel returns the exits' values too, computed as ``march._exit``
computes them. The G-buffer kernel computes ``gbuffer._layer``'s float64 attributes per
pixel (the G-buffer carries no gradient). The cone kernels compute what ``rousiers``
derives from its four marched bounding rays (their screen footprint, and the spread they
give the exit lobe) where no gradient flows through them. tests/test_native.py checks that
exits, layers, footprints, spreads and images are identical to the tensor code's.

The kernels are plain C (no Python or torch headers), threaded with OpenMP where the
compiler has it (then on torch's own thread pool, csrc/common.h), else with pthreads. The
first call of a machine compiles them with the system C compiler (``$CC``, else
``cc``/``gcc``; about a second) into the cache folder (``$TORCHREFRACT_CACHE`` or
``~/.cache/torchrefract``, ``native/``), keyed by the sources, the flags and the
platform. Where no compiler is found or the build fails, a warning names the reason once
and the tensor code runs instead (the same images, slower). On by default; a render's
:class:`~torchrefract.settings.RenderSettings` (``native``, ``native_simd``) turns them off.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from torchrefract import settings
from torchrefract.output.atomic import atomic_path

SOURCES = tuple(Path(__file__).with_name("csrc") / f for f in ("march.c", "gbuffer.c",
                                                                "cone.c", "specular.c",
                                                                "background.c", "rousiers.c",
                                                                "lean.c", "raster.c",
                                                                "lattice.c", "relight.c",
                                                                "box.c", "materials.c",
                                                                "index.c"))
HEADERS = tuple(Path(__file__).with_name("csrc") / f  # part of the cache key
                for f in ("common.h", "march_core.h", "optics.h", "sgtable.h",
                          "lighting.h", "materials.h", "frame.h", "bounces.h",
                          "rousiers_core.h", "subpixels.h"))
# No fast-math and no contraction: every float32 operation rounds as torch's elementwise
# ops do (the one fused multiply-add, in torch.cross, is written out as fmaf in the source).
# With -march=native where the compiler takes it: this CPU's instructions (fmaf inline,
# AVX2), the same values, ~12% faster fused kernels; the library is keyed by the CPU's
# flags too (_cpu_key), so a cache folder shared by machines of different CPUs keeps one
# build per CPU.
FLAGS = ("-O3", "-shared", "-fPIC", "-pthread", "-ffp-contract=off", "-fno-fast-math")

_LOCK = threading.Lock()
_LIB: ctypes.CDLL | None = None
_FAILED: str | None = None


def set_native(enabled: bool) -> None:
    """Deprecated: pass ``RenderSettings(native=...)`` to the render instead."""
    settings.deprecated_switch("set_native", "native", "TORCHREFRACT_NATIVE", enabled)


def native_enabled() -> bool:
    """Whether the current settings ask for the native kernels."""
    return settings.current().native


class _Job(ctypes.Structure):
    """ctypes mirror of ``Job`` in csrc/march.c (the field order and types must match; the
    loader checks the size against the library's own)."""

    _fields_ = [
        ("n", ctypes.c_int64),
        ("c0", ctypes.c_void_p), ("ct", ctypes.c_void_p),
        ("s_max", ctypes.c_void_p), ("s_min", ctypes.c_void_p),
        ("sx_v", ctypes.c_void_p), ("sy_v", ctypes.c_void_p),
        ("batch", ctypes.c_void_p),
        ("planes", ctypes.c_void_p), ("plane_base", ctypes.c_void_p), ("pw", ctypes.c_int),
        ("h", ctypes.c_int64), ("w", ctypes.c_int64),
        ("steps", ctypes.c_int), ("refine", ctypes.c_int),
        ("p1", ctypes.c_void_p), ("t", ctypes.c_void_p),
        ("tri_front", ctypes.c_void_p), ("tri_back", ctypes.c_void_p),
        ("tv", ctypes.c_void_p), ("across", ctypes.c_void_p),
        ("walk_steps", ctypes.c_int),
        ("simd", ctypes.c_int),
        ("tn", ctypes.c_void_p),
        ("s_out", ctypes.c_void_p), ("bary_out", ctypes.c_void_p),
        ("normal_out", ctypes.c_void_p), ("pos_out", ctypes.c_void_p),
        ("found", ctypes.c_void_p), ("tri", ctypes.c_void_p), ("layer", ctypes.c_void_p),
    ]


class _LayerJob(ctypes.Structure):
    """ctypes mirror of ``LayerJob`` in csrc/gbuffer.c."""

    _fields_ = [
        ("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
        ("ids", ctypes.c_void_p), ("eye", ctypes.c_void_p), ("dirs", ctypes.c_void_p),
        ("forward", ctypes.c_void_p), ("tv", ctypes.c_void_p), ("tn", ctypes.c_void_p),
        ("tuv", ctypes.c_void_p), ("neighbors", ctypes.c_void_p),
        ("back", ctypes.c_int), ("tol", ctypes.c_double), ("keep_tol", ctypes.c_double),
        ("mask", ctypes.c_void_p), ("tri", ctypes.c_void_p),
        ("position", ctypes.c_void_p), ("dist", ctypes.c_void_p), ("depth", ctypes.c_void_p),
        ("bary", ctypes.c_void_p),
        ("normal", ctypes.c_void_p), ("uv", ctypes.c_void_p),
    ]


class _FootprintJob(ctypes.Structure):
    """ctypes mirror of ``FootprintJob`` in csrc/cone.c."""

    _fields_ = [
        ("n", ctypes.c_int64), ("q", ctypes.c_void_p), ("ok", ctypes.c_void_p),
        ("pc", ctypes.c_void_p), ("proj", ctypes.c_void_p), ("batch", ctypes.c_void_p),
        ("xy", ctypes.c_void_p), ("xy_c", ctypes.c_void_p), ("ext", ctypes.c_void_p),
    ]


class _SpreadJob(ctypes.Structure):
    """ctypes mirror of ``SpreadJob`` in csrc/cone.c."""

    _fields_ = [
        ("n", ctypes.c_int64), ("p", ctypes.c_void_p), ("n_c", ctypes.c_void_p),
        ("dirs", ctypes.c_void_p), ("n4", ctypes.c_void_p), ("ok", ctypes.c_void_p),
        ("ior", ctypes.c_void_p), ("fallback", ctypes.c_void_p), ("two_ln4", ctypes.c_float),
        ("stage", ctypes.c_int), ("root_arg", ctypes.c_void_p), ("root", ctypes.c_void_p),
        ("var", ctypes.c_void_p),
    ]


_p = ctypes.c_void_p


class _Lights(ctypes.Structure):
    """ctypes mirror of ``Lights`` in csrc/lighting.h."""

    _fields_ = [("tex", _p), ("tex_h", _p), ("tex_w", _p), ("rot_cos", _p), ("rot_sin", _p),
                ("scale", _p),
                ("nl", ctypes.c_int64), ("light_pos", _p), ("light_r", _p), ("light_le", _p),
                ("gl_x", _p), ("gl_w", _p), ("gl_n", ctypes.c_int64)]


class _SgTable(ctypes.Structure):
    """ctypes mirror of ``SgTable`` in csrc/sgtable.h."""

    _fields_ = [("vol", _p), ("dvol", _p), ("vol_l2", _p), ("evol", _p),
                ("nt", ctypes.c_int64), ("ne", ctypes.c_int64),
                ("na", ctypes.c_int64)] + [
        (f, ctypes.c_float) for f in ("eta_max", "la0", "la1", "alpha_min", "alpha_floor",
                                      "log_k_min", "log_k_max")]


class _SgEnv(ctypes.Structure):
    """ctypes mirror of ``SgEnv`` in csrc/lighting.h."""

    _fields_ = [("base", _p), ("atlas", _p), ("meta", _p), ("base_hw", _p), ("atlas_hw", _p)]


class _Frame(ctypes.Structure):
    """ctypes mirror of ``Frame`` in csrc/frame.h (shading/fused.py fills it)."""

    _fields_ = [("n", ctypes.c_int64), ("nb", ctypes.c_int64)] + [(f, _p) for f in (
        "idx", "batch", "ray_dir", "front_pos", "front_normal", "front_dist", "back_dist",
        "eye", "basis", "proj", "sphere_c", "sphere_r")] + [
        ("march", _Job), ("ior", _p), ("alpha", _p), ("absorption", _p), ("dist", _p),
        ("tir_mode", ctypes.c_int), ("rough", ctypes.c_int), ("rmap", _p), ("rmap_hw", _p),
        ("rrange", _p), ("front_uv", _p), ("tri_uvs", _p), ("table", _SgTable), ("esc", _p),
        ("esc_n", ctypes.c_int64), ("lights", _Lights), ("env", _SgEnv), ("radiance", _p),
        ("exit_found", _p), ("tir", _p)]


class _Bounces(ctypes.Structure):
    """ctypes mirror of ``Bounces`` in csrc/bounces.h."""

    _fields_ = [("limit", ctypes.c_int), ("rays", ctypes.c_int), ("steps", ctypes.c_int),
                ("tol", ctypes.c_float), ("bounces", _p), ("residual", _p)]


class _SpecJob(ctypes.Structure):
    """ctypes mirror of ``SpecJob`` in csrc/specular.c."""

    _fields_ = [("f", _Frame), ("blur", ctypes.c_int), ("blur_sigma", _p), ("bo", _Bounces)]


class _RousJob(ctypes.Structure):
    """ctypes mirror of ``RousJob`` in csrc/rousiers.c."""

    _fields_ = [("f", _Frame), ("cone_steps", ctypes.c_int), ("cone_refine", ctypes.c_int),
                ("two_ln4", ctypes.c_float), ("lobe_sigma", _p), ("footprint", _p),
                ("bo", _Bounces), ("diffuse_var", ctypes.c_float),
                ("levels", ctypes.c_int), ("mips", ctypes.c_int),
                ("level_alpha", _p), ("cover", _p), ("cover_hw", _p),
                ("plane", ctypes.c_int), ("back_normal", _p), ("back_mask", _p),
                ("h", ctypes.c_int64), ("w", ctypes.c_int64)]


class _BackgroundJob(ctypes.Structure):
    """ctypes mirror of ``BackgroundJob`` in csrc/background.c."""

    _fields_ = [("b", ctypes.c_int64), ("hw", ctypes.c_int64), ("ray_dir", _p), ("eye", _p),
                ("front_mask", _p), ("front_dist", _p), ("lights", _Lights), ("out", _p)]


class _Folds(ctypes.Structure):
    """ctypes mirror of ``Folds`` in csrc/subpixels.h."""

    _fields_ = [("face_normal", _p), ("tv", _p), ("tn", _p), ("normal_tol", ctypes.c_float),
                ("face_tol", ctypes.c_float)]


class _RasterJob(ctypes.Structure):
    """ctypes mirror of ``RasterJob`` in csrc/raster.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("vertices", _p), ("faces", _p), ("views", _p), ("mvp", _p),
                ("front", _p), ("back", _p), ("row0", ctypes.c_int64),
                ("rows", ctypes.c_int64), ("ids32", ctypes.c_int), ("sub_n", ctypes.c_int64),
                ("flags", _p), ("folds", _Folds)]


class _SubFlagsJob(ctypes.Structure):
    """ctypes mirror of ``SubFlagsJob`` in csrc/raster.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("n", ctypes.c_int64), ("front", _p), ("back", _p), ("folds", _Folds),
                ("out", _p)]


class _RoughnessJob(ctypes.Structure):
    """ctypes mirror of ``RoughnessJob`` in csrc/materials.c."""

    _fields_ = [("n", ctypes.c_int64), ("batch", _p), ("uv", _p), ("alpha", _p),
                ("maps", _p), ("hw", _p), ("range", _p), ("out", _p)]


class _CoverageJob(ctypes.Structure):
    """ctypes mirror of ``CoverageJob`` in csrc/materials.c."""

    _fields_ = [("r", _RoughnessJob), ("hw", ctypes.c_int64), ("levels", ctypes.c_int64),
                ("mask", _p), ("out", _p)]


class _CoverJob(ctypes.Structure):
    """ctypes mirror of ``CoverJob`` in csrc/background.c."""

    _fields_ = [("n", ctypes.c_int64), ("nl", ctypes.c_int64), ("o", _p), ("d", _p),
                ("k", _p), ("pos", _p), ("r", _p), ("gl_x", _p), ("gl_w", _p),
                ("gl_n", ctypes.c_int64), ("out", _p)]


class _LobesJob(ctypes.Structure):
    """ctypes mirror of ``LobesJob`` in csrc/rousiers.c (shading/fused.py fills it)."""

    _fields_ = [("table", _SgTable), ("n", ctypes.c_int64), ("front", ctypes.c_int),
                ("view", _p), ("n1", _p), ("cos", _p), ("eta", _p), ("alpha", _p),
                ("var", _p), ("dist", _p), ("e_r", _p), ("k_r", _p), ("axis_r", _p),
                ("e_t", _p), ("k_t", _p), ("p_t", _p)]


class _IncidentJob(ctypes.Structure):
    """ctypes mirror of ``IncidentJob`` in csrc/background.c (shading/fused.py fills it)."""

    _fields_ = [("lights", _Lights), ("env", _SgEnv), ("n", ctypes.c_int64), ("batch", _p),
                ("o", _p), ("d", _p), ("k", _p), ("out", _p)]


class _I0eJob(ctypes.Structure):
    """ctypes mirror of ``I0eJob`` in csrc/background.c."""

    _fields_ = [("n", ctypes.c_int64), ("x", _p), ("out", _p)]


class _RefractX4Job(ctypes.Structure):
    """ctypes mirror of ``RefractX4Job`` in csrc/cone.c."""

    _fields_ = [("n", ctypes.c_int64), ("d", _p), ("nrm", _p), ("eta", _p), ("lanes", _p),
                ("scalar", _p)]


class _Theta3Job(ctypes.Structure):
    """ctypes mirror of ``Theta3Job`` in csrc/cone.c."""

    _fields_ = [("n", ctypes.c_int64), ("cs", _p), ("eta", _p), ("lanes", _p), ("scalar", _p)]


class _TriPlanesJob(ctypes.Structure):
    """ctypes mirror of ``TriPlanesJob`` in csrc/march.c."""

    _fields_ = [("n", ctypes.c_int64), ("nv", ctypes.c_int64), ("first", _p), ("face0", _p),
                ("tv", _p), ("eye", _p), ("basis", _p), ("out", _p)]


class _LatticeJob(ctypes.Structure):
    """ctypes mirror of ``LatticeJob`` in csrc/lattice.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("front_mask", _p), ("back_mask", _p), ("front_normal", _p),
                ("back_normal", _p), ("back_depth", _p), ("alpha", _p),
                ("per_pixel", ctypes.c_int), ("alpha_min", ctypes.c_float),
                ("normal_tol", ctypes.c_float), ("depth_tol", ctypes.c_float),
                ("rtol", ctypes.c_float), ("radiance", _p), ("status", _p), ("gap", _p),
                ("weight", _p), ("blend_from", ctypes.c_float),
                ("npass", ctypes.c_int), ("pass_ptr", _p), ("pass_ch", _p),
                ("stride", ctypes.c_int64), ("fh", ctypes.c_int64), ("fw", ctypes.c_int64),
                ("uniform", _p), ("counts", _p)]


class _BoxesJob(ctypes.Structure):
    """ctypes mirror of ``BoxesJob`` in csrc/box.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("nitems", ctypes.c_int64), ("masks", _p * 2), ("uniform", _p), ("x", _p),
                ("out", _p), ("c", _p), ("mask_of", _p), ("use_uniform", _p)]


class _BoxJob(ctypes.Structure):
    """ctypes mirror of ``BoxJob`` in csrc/box.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("n", ctypes.c_int64), ("c", ctypes.c_int64), ("x", _p), ("mask", _p),
                ("uniform", _p), ("out", _p)]


class _OneSampleJob(ctypes.Structure):
    """ctypes mirror of ``OneSampleJob`` in csrc/box.c."""

    _fields_ = [("n", ctypes.c_int64), ("hw", ctypes.c_int64), ("front_mask", _p),
                ("back_mask", _p), ("front_dist", _p), ("back_dist", _p), ("rough", _p),
                ("per_pixel", ctypes.c_int), ("ior", _p), ("coverage", _p),
                ("thickness", _p), ("roughness", _p), ("ior_out", _p)]


class _MipsJob(ctypes.Structure):
    """ctypes mirror of ``MipsJob`` in csrc/box.c."""

    _fields_ = [("b", ctypes.c_int64), ("c", ctypes.c_int64), ("nlevels", ctypes.c_int64),
                ("hw", _p), ("out", _p), ("level", ctypes.c_int64)]


class _RefineJob(ctypes.Structure):
    """ctypes mirror of ``RefineJob`` in csrc/lattice.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("n", ctypes.c_int64), ("uniform", _p), ("radiance", _p),
                ("rtol", ctypes.c_float), ("more", _p)]


class _EdgesJob(ctypes.Structure):
    """ctypes mirror of ``EdgesJob`` in csrc/lattice.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("front_mask", _p), ("back_mask", _p),
                ("front_normal", _p), ("back_normal", _p), ("back_depth", _p),
                ("sub", _p), ("alpha", _p),
                ("per_pixel", ctypes.c_int), ("smooth_alpha", ctypes.c_float),
                ("normal_tol", ctypes.c_float), ("depth_tol", ctypes.c_float),
                ("pairs", _p), ("edge", _p)]


class _UniformJob(ctypes.Structure):
    """ctypes mirror of ``UniformJob`` in csrc/lattice.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("n", ctypes.c_int64), ("front_mask", _p), ("back_mask", _p),
                ("front_normal", _p), ("back_normal", _p), ("back_depth", _p), ("alpha", _p),
                ("per_pixel", ctypes.c_int), ("smooth_alpha", ctypes.c_float),
                ("normal_tol", ctypes.c_float), ("depth_tol", ctypes.c_float),
                ("uniform", _p), ("region", _p), ("shade", _p)]


class _RaysJob(ctypes.Structure):
    """ctypes mirror of ``RaysJob`` in csrc/gbuffer.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("r0", ctypes.c_int64), ("rows", ctypes.c_int64), ("frame", _p), ("out", _p)]


class _RaysAtJob(ctypes.Structure):
    """ctypes mirror of ``RaysAtJob`` in csrc/gbuffer.c."""

    _fields_ = [("b", ctypes.c_int64), ("m", ctypes.c_int64), ("h", ctypes.c_int64),
                ("w", ctypes.c_int64), ("frame", _p), ("rows", _p), ("cols", _p), ("out", _p)]


class _PutRowsJob(ctypes.Structure):
    """ctypes mirror of ``PutRowsJob`` in csrc/box.c."""

    _fields_ = [("n", ctypes.c_int64), ("nbuf", ctypes.c_int64), ("dst", _p), ("out", _p),
                ("src", _p), ("ch", _p)]


class _CenterJob(ctypes.Structure):
    """ctypes mirror of ``CenterJob`` in csrc/gbuffer.c."""

    _fields_ = [("b", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("n", ctypes.c_int64)] + [(f, _p) for f in (
                    "uniform", "center_dirs", "eye", "proj", "tv", "tn", "tuv", "tri",
                    "position", "dist", "depth", "bary", "normal", "uv", "ray_dir")]


class _MaskJob(ctypes.Structure):
    """ctypes mirror of ``MaskJob`` in csrc/index.c."""

    _fields_ = [("n", ctypes.c_int64), ("hw", ctypes.c_int64), ("block", ctypes.c_int64),
                ("mask", _p), ("first", _p), ("total", ctypes.c_int64), ("idx", _p),
                ("view", _p)]


class _WaitJob(ctypes.Structure):
    """ctypes mirror of ``WaitJob`` in csrc/index.c."""

    _fields_ = [(f, ctypes.c_int64) for f in ("b", "h", "w", "stride", "fh", "fw")] + [
        ("status", _p), ("mask", _p)]


class _SlotsJob(ctypes.Structure):
    """ctypes mirror of ``SlotsJob`` in csrc/index.c."""

    _fields_ = [(f, ctypes.c_int64) for f in ("b", "h", "w", "n", "k")] + [
        (f, _p) for f in ("idx", "first", "count", "ids0", "ids1", "pixels", "rows", "cols",
                          "sid0", "sid1", "flat", "taken")]


class _PutIdsJob(ctypes.Structure):
    """ctypes mirror of ``PutIdsJob`` in csrc/index.c."""

    _fields_ = [("m", ctypes.c_int64)] + [
        (f, _p) for f in ("flat", "taken", "tri0", "tri1", "ids0", "ids1")]


class _ShadeLevel(ctypes.Structure):
    """ctypes mirror of ``ShadeLevel`` in csrc/lattice.c."""

    _fields_ = [("stride", ctypes.c_int64), ("h", ctypes.c_int64), ("w", ctypes.c_int64),
                ("status", _p), ("gap", _p), ("rtol", ctypes.c_float)]


class _LatticeShadeJob(ctypes.Structure):
    """ctypes mirror of ``LatticeShadeJob`` in csrc/lattice.c."""

    _fields_ = [("run", _p), ("job", _p), ("b", ctypes.c_int64), ("h", ctypes.c_int64),
                ("w", ctypes.c_int64), ("nlevels", ctypes.c_int), ("levels", _p),
                ("blend_from", ctypes.c_float), ("radiance", _p), ("npass", ctypes.c_int),
                ("pass_ptr", _p), ("pass_ch", _p)]


class _RelightJob(ctypes.Structure):
    """ctypes mirror of ``RelightJob`` in csrc/relight.c."""

    _fields_ = [("n", ctypes.c_int64), ("u0", _p), ("view", _p), ("rot", _p),
                ("nrot", ctypes.c_int64), ("u", _p), ("lobe", _p), ("plain", ctypes.c_int),
                ("w_map", ctypes.c_int64), ("cols", ctypes.c_int64), ("last", ctypes.c_int64),
                ("x0p1", _p), ("w", _p),
                ("row", _p), ("sn", _p), ("idx", _p), ("wts", _p), ("tex", _p),
                ("vals", _p), ("status", _p)]


_KERNELS = {"march": _Job, "tri_planes": _TriPlanesJob, "layer": _LayerJob,
            "footprint": _FootprintJob,
            "spread": _SpreadJob, "refract_x4": _RefractX4Job, "theta3": _Theta3Job,
            "i0e": _I0eJob,
            "light_coverage": _CoverJob, "incident_sg": _IncidentJob, "lobes": _LobesJob,
            "roughness": _RoughnessJob,
            "level_coverage": _CoverageJob, "specular": _SpecJob,
            "background": _BackgroundJob, "rousiers": _RousJob, "raster": _RasterJob,
            "lattice_plan": _LatticeJob, "lattice_fill": _LatticeJob,
            "lattice_shade": _LatticeShadeJob, "uniform": _UniformJob, "refine": _RefineJob,
            "edges": _EdgesJob, "sub_flags": _SubFlagsJob,
            "box": _BoxJob,
            "boxes": _BoxesJob, "one_sample": _OneSampleJob, "mips": _MipsJob,
            "center_samples": _CenterJob, "pixel_rays": _RaysJob, "rays_at": _RaysAtJob,
            "put_rows": _PutRowsJob, "mask_count": _MaskJob, "mask_index": _MaskJob,
            "clear_waiting": _WaitJob, "sample_slots": _SlotsJob, "put_ids": _PutIdsJob,
            "relight_reads": _RelightJob}
"""Entry point ``torchrefract_<name>(job*, threads)`` -> its job's ctypes mirror."""


def _compiler() -> str | None:
    cc = os.environ.get("CC")
    if cc and shutil.which(cc.split()[0]):
        return cc
    for name in ("cc", "gcc", "clang"):
        if shutil.which(name):
            return name
    return None


def _cpu_key() -> str:
    """The CPU's model and instruction-set flags (Linux: /proc/cpuinfo), for the cache key
    of a library built with -march=native."""
    try:
        with open("/proc/cpuinfo") as f:
            lines = [l for l in f if l.startswith(("model name", "flags"))][:2]
    except OSError:
        lines = [platform.processor()]
    return hashlib.sha256("".join(lines).encode()).hexdigest()[:16]


def library_path(cache_dir: str | Path | None = None, name: str = "kernels",
                 sources: tuple[Path, ...] | None = None,
                 headers: tuple[Path, ...] | None = None) -> Path:
    """Where a library built from ``sources`` (and ``headers``, part of the key) lives for
    these sources, flags and platform (None: :data:`SOURCES`, :data:`HEADERS`)."""
    sources = SOURCES if sources is None else sources
    headers = HEADERS if headers is None else headers
    h = hashlib.sha256(b"".join(src.read_bytes() for src in sources + headers))
    h.update(repr((FLAGS, platform.machine(), sys.platform, _compiler(), _cpu_key())
                  ).encode())
    root = Path(cache_dir) if cache_dir is not None else settings.cache_folder()
    return root / "native" / f"{name}_{h.hexdigest()[:16]}.so"


def build(cache_dir: str | Path | None = None, name: str = "kernels",
          sources: tuple[Path, ...] | None = None,
          headers: tuple[Path, ...] | None = None) -> Path:
    """Compile ``sources`` into one library in the cache (if not there yet); returns its
    path (default: the kernels of this module; ``methods/sh/native.py`` builds its own
    with this recipe).

    Raises:
        RuntimeError: no C compiler, or the compile failed (its output quoted).
    """
    sources = SOURCES if sources is None else sources
    out = library_path(cache_dir, name, sources, headers)
    if out.exists():
        return out
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set $CC, or install gcc: "
                           "apt-get install gcc)")
    print(f"torchrefract: compiling the native {name} into {out.parent} (once per machine "
          f"and version, a few seconds)", file=sys.stderr, flush=True)
    # The compiler writes a temporary file, renamed when complete: a concurrent process sees
    # no half-written library.
    with atomic_path(out, suffix=".so") as tmp:
        # With OpenMP where the compiler has it (csrc/common.h: torch's thread pool), else
        # with pthreads alone; the first set of flags the compiler takes is used, and an
        # error in the sources is raised, not built around with fewer flags (which would
        # drop the AVX2 paths without a word).
        extra = next(x for x in EXTRA_FLAGS if x == [] or _accepts(cc, tuple(x)))
        cmd = (cc.split() + list(FLAGS) + extra + ["-o", str(tmp)]
               + [str(src) for src in sources] + ["-lm"])
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed (exit {proc.returncode}): "
                               f"{(proc.stderr or proc.stdout).strip()[-1500:]}")
    return out


EXTRA_FLAGS = (["-march=native", "-fopenmp"], ["-fopenmp"], ["-march=native"], [])
"""The flags tried after :data:`FLAGS`, in order: the first set the compiler accepts
(:func:`_accepts`) builds the kernels."""


@functools.lru_cache(maxsize=None)
def _accepts(cc: str, extra: tuple[str, ...]) -> bool:
    """Whether ``cc`` builds a trivial library with :data:`FLAGS` and ``extra``: a flag it
    lacks, not an error in the kernels' sources, moves :func:`build` to the next set. A
    probe that could not run (a timeout on a loaded machine) raises: a library built with
    fewer flags would stay in the cache."""
    with tempfile.TemporaryDirectory() as d:
        src = Path(d) / "probe.c"
        src.write_text("int torchrefract_probe(void) { return 0; }\n")
        cmd = cc.split() + list(FLAGS) + list(extra) + ["-o", str(Path(d) / "probe.so"),
                                                        str(src)]
        try:
            return subprocess.run(cmd, capture_output=True, timeout=120).returncode == 0
        except (OSError, subprocess.TimeoutExpired) as exc:
            raise RuntimeError(f"the compiler probe {' '.join(cmd)} did not run: {exc}") \
                from exc


def bind(lib: ctypes.CDLL, kernels: dict[str, type]) -> None:
    """Declare each entry point ``torchrefract_<name>(job*, threads) -> int`` of ``lib``
    (``kernels``: name -> its job's ctypes mirror), checking each mirror's size against
    the library's ``torchrefract_<name>_job_size()``.

    Raises:
        RuntimeError: a job layout differs from its mirror.
    """
    for name, job in kernels.items():
        fn = getattr(lib, f"torchrefract_{name}")
        fn.argtypes = [ctypes.POINTER(job), ctypes.c_int]
        fn.restype = ctypes.c_int
        size = getattr(lib, f"torchrefract_{name}_job_size")
        size.restype = ctypes.c_int64
        if size() != ctypes.sizeof(job):
            raise RuntimeError(f"the library's {name} job layout differs from its ctypes "
                               f"mirror")


def _load() -> ctypes.CDLL | None:
    global _LIB, _FAILED
    if _LIB is not None or _FAILED is not None:
        return _LIB
    with _LOCK:
        if _LIB is None and _FAILED is None:
            try:
                lib = ctypes.CDLL(str(build()))
                bind(lib, _KERNELS)
                _LIB = lib
            except Exception as exc:  # noqa: BLE001  (any build or load failure: fall back)
                _FAILED = f"{type(exc).__name__}: {exc}"
                warnings.warn(f"torchrefract: the native kernels (march, G-buffer, cone) are "
                              f"unavailable, using the tensor code (same images, slower): "
                              f"{_FAILED}", RuntimeWarning, stacklevel=3)
    return _LIB


def failure() -> str | None:
    """Why the kernels did not build or load (None where they did, or were not tried)."""
    return _FAILED


def available() -> bool:
    """Whether the kernels run now: enabled, built and loaded (the first call builds
    them)."""
    return settings.current().native and _load() is not None


def no_grad_through(*tensors: torch.Tensor) -> bool:
    """Whether no gradient is wanted through ``tensors`` (the kernels have no backward:
    where one is, the callers run their tensor code)."""
    return not torch.is_grad_enabled() or not any(t.requires_grad for t in tensors)


def _call(name: str, job: ctypes.Structure, lib: ctypes.CDLL | None = None) -> bool:
    """Run kernel ``torchrefract_<name>`` of ``lib`` (None: these kernels) on ``job`` with
    torch's thread count; ``False`` where a thread could not be started (the caller then
    runs its tensor code)."""
    return getattr(lib or _LIB, f"torchrefract_{name}")(ctypes.byref(job),
                                                        torch.get_num_threads()) == 0


def entry(name: str, lib: ctypes.CDLL | None = None) -> int:
    """The address of kernel ``torchrefract_<name>`` of ``lib`` (None: these kernels,
    loaded: :func:`available`), for a job that calls it (csrc/lattice.c's driver)."""
    return ctypes.cast(getattr(lib or _LIB, f"torchrefract_{name}"), ctypes.c_void_p).value


def as_input(x: torch.Tensor) -> torch.Tensor:
    """``x`` contiguous and out of autograd, for a kernel to read: ``x`` itself where it
    already is (no op dispatched: a render's ~100 inputs cost a detach each otherwise,
    ~5 us apiece between kernels)."""
    if x.requires_grad:
        x = x.detach()
    return x if x.is_contiguous() else x.contiguous()


def _inputs(f32: tuple[torch.Tensor, ...], i64: tuple[torch.Tensor, ...],
            b8: tuple[torch.Tensor, ...] = ()) -> list[torch.Tensor] | None:
    """The kernels' inputs, detached and contiguous, in order (float32, int64, bool
    tensors on the CPU); ``None`` where one is of another dtype or device."""
    ok = (all(x.dtype == torch.float32 for x in f32) and all(x.dtype == torch.int64 for x in i64)
          and all(x.dtype == torch.bool for x in b8)
          and all(x.device.type == "cpu" for x in f32 + i64 + b8))
    return [as_input(x) for x in f32 + i64 + b8] if ok else None


def march_fields(planes, both: bool) -> dict | None:
    """The march job's fields of a ``march.Marched`` (its tables and the marched layers'
    triangle ids; ``both``: the front layer's too), the tensors kept under ``"keep"``;
    ``None`` where a tensor is not on the CPU or of its dtype."""
    front = planes.front if both else None
    ok = (planes.table.dtype == torch.float32 and planes.base.dtype == torch.int64
          and planes.back.dtype == torch.int32
          and (front is None or front.dtype == torch.int32)
          and all(x.device.type == "cpu" for x in (planes.table, planes.base, planes.back)))
    if not ok:
        return None
    table, base, back = (as_input(x) for x in (planes.table, planes.base, planes.back))
    front = back if front is None else as_input(front)  # (not read: pw 4)
    # the AVX2 search gathers with 32-bit indices: the pixels' and the plane rows'
    simd = int(settings.current().native_simd and back.numel() < 2**31
               and table.numel() < 2**31)
    return dict(planes=table.data_ptr(), plane_base=base.data_ptr(), pw=8 if both else 4,
                h=planes.h, w=planes.w, tri_front=front.data_ptr(),
                tri_back=back.data_ptr(), simd=simd, keep=(table, base, back, front))


def tri_planes(tv: torch.Tensor, face0, count, eye: torch.Tensor,
               basis: torch.Tensor) -> torch.Tensor | None:
    """``march.plane_table``'s rows of V views in one call, (sum of ``count``, 4) float32,
    computed in double as the tensor code does (the same table within float64 rounding);
    ``None`` where the kernel is unavailable or an input is not a CPU tensor of its dtype.

    Args:
        tv: (T, 3, 3) the batch's triangles; face0, count: V whole numbers each (a list or
            an int64 tensor), view v's triangles are ``tv[face0[v]:face0[v] + count[v]]``;
            eye: (V, 3); basis: (V, 9) rows right, up, forward.
    """
    if not available():
        return None
    keep = _inputs((tv, eye, basis), ())
    if keep is None:
        return None
    tv, eye, basis = keep
    face0, count = ([int(x) for x in (v.tolist() if isinstance(v, torch.Tensor) else v)]
                    for v in (face0, count))
    first = [0]
    for c in count:
        first.append(first[-1] + c)
    ints = torch.tensor(face0 + first, dtype=torch.int64)  # one tensor: face0, then first
    out = torch.empty(first[-1], 4)
    if out.shape[0] == 0:
        return out
    job = _TriPlanesJob(n=out.shape[0], nv=len(count), first=ints.data_ptr() + 8 * len(face0),
                        face0=ints.data_ptr(), tv=tv.data_ptr(), eye=eye.data_ptr(),
                        basis=basis.data_ptr(), out=out.data_ptr())
    return out if _call("tri_planes", job) else None


def march(c0: torch.Tensor, ct: torch.Tensor, s_max: torch.Tensor, s_min: torch.Tensor,
          sx_v: torch.Tensor, sy_v: torch.Tensor, batch: torch.Tensor, planes, both: bool,
          steps: int, refine: int, p1: torch.Tensor, t: torch.Tensor, tv: torch.Tensor,
          across: torch.Tensor, walk_steps: int = 16, tri_normals: torch.Tensor | None = None
          ) -> tuple[torch.Tensor, ...] | None:
    """The search, bisections, exit candidates and walk of ``march._march`` (its
    ``depth_min=None`` form) for N rays; ``None`` where the kernel is unavailable or an
    input is not a float32 / int64 CPU tensor (the caller then marches in torch).

    Args:
        c0, ct: (N, 3) camera coordinates of the start and per unit s.
        s_max, s_min: (N,) the bounding chord and the smallest accepted exit distance.
        sx_v, sy_v: (B,) per-view pixel scales (``0.5 w / tan``, ``0.5 h / tan``).
        batch: (N,) int64 view per ray. planes: the ``march.Marched`` layers (the frame,
            its triangle ids and plane tables); both: march between the two layers
            (``march_inside``), else through the back layer.
        steps, refine: the uniform samples and bisections.
        p1, t: (N, 3) world start points and directions.
        tv: (T, 3, 3) vertices; across: (T, 3) int64 (``MeshData.across``).
        walk_steps: the most edges a walk crosses.
        tri_normals: (T, 3, 3) corner shading normals: also return the exits' values
            (for callers that need no gradient through them).

    Returns:
        found (N,) bool, tri (N,) int64 (-1 where not found), layer (N,) int64 (0 front,
        1 back, -1); with ``tri_normals`` also the distance (N,), barycentrics (N, 3),
        unit shading normal (N, 3) and position (N, 3) of each exit (zeros, and p1, where
        none was found), as ``march._exit`` computes them.
    """
    if not available():
        return None
    values = tri_normals is not None
    tn = tri_normals if values else tv  # (not read without values)
    keep = _inputs((c0, ct, s_max, s_min, sx_v, sy_v, p1, t, tv, tn), (batch, across))
    fields = march_fields(planes, both)
    if keep is None or fields is None:
        return None
    c0, ct, s_max, s_min, sx_v, sy_v, p1, t, tv, tn, batch, across = keep
    held = fields.pop("keep")  # noqa: F841 (alive until the call returns)
    n = c0.shape[0]
    found = torch.empty(n, dtype=torch.bool)
    tri = torch.empty(n, dtype=torch.int64)
    layer = torch.empty(n, dtype=torch.int64)
    extra = ((torch.empty(n), torch.empty(n, 3), torch.empty(n, 3), torch.empty(n, 3))
             if values else ())
    if n == 0:
        return (found, tri, layer) + extra
    ptrs = [x.data_ptr() for x in extra] if values else [None] * 4
    job = _Job(n=n, c0=c0.data_ptr(), ct=ct.data_ptr(), s_max=s_max.data_ptr(),
               s_min=s_min.data_ptr(), sx_v=sx_v.data_ptr(), sy_v=sy_v.data_ptr(),
               batch=batch.data_ptr(), steps=steps, refine=refine, p1=p1.data_ptr(),
               t=t.data_ptr(), tv=tv.data_ptr(), across=across.data_ptr(),
               walk_steps=walk_steps, tn=tn.data_ptr(),
               s_out=ptrs[0], bary_out=ptrs[1], normal_out=ptrs[2], pos_out=ptrs[3],
               found=found.data_ptr(), tri=tri.data_ptr(), layer=layer.data_ptr(), **fields)
    if not _call("march", job):
        return None  # a thread could not be started: march in torch
    return (found, tri, layer) + extra


def layer(ids: torch.Tensor, eye: torch.Tensor, dirs: torch.Tensor, forward: torch.Tensor,
          tri_vertices: torch.Tensor, tri_normals: torch.Tensor, tri_uvs: torch.Tensor,
          tri_neighbors: torch.Tensor, back: bool, tol: float, keep_tol: float,
          points: bool = True) -> dict[str, torch.Tensor | None] | None:
    """``gbuffer._layer``'s exact attributes of one layer (with its edge repair), or
    ``None`` where the kernel is unavailable or an input is not float32 / int64 on the CPU.

    Args:
        ids: (B, H, W) int64 rasterized global face ids (-1 empty). eye, forward: (B, 3).
        dirs: (B, H, W, 3) pixel rays. tri_vertices, tri_normals: (F, 3, 3); tri_uvs:
            (F, 3, 2); tri_neighbors: (F, 3) int64 (``MeshBatch``).
        back: the back-face layer. tol, keep_tol: ``_repair_edge_ids``' tolerances.
        points: make the position and the barycentrics (else None, not computed).

    Returns:
        The ``Layer`` fields: mask (B, H, W) bool, tri (B, H, W) int32, position, bary,
        normal (B, H, W, 3), dist, depth (B, H, W), uv (B, H, W, 2), float32.
    """
    if not available():
        return None
    keep = _inputs((eye, dirs, forward, tri_vertices, tri_normals, tri_uvs),
                   (ids, tri_neighbors))
    if keep is None:
        return None
    eye, dirs, forward, tri_vertices, tri_normals, tri_uvs, ids, tri_neighbors = keep
    b, h, w = ids.shape
    out = {"mask": torch.empty(b, h, w, dtype=torch.bool),
           "tri": torch.empty(b, h, w, dtype=torch.int32),
           "position": torch.empty(b, h, w, 3) if points else None,
           "dist": torch.empty(b, h, w),
           "depth": torch.empty(b, h, w), "bary": torch.empty(b, h, w, 3) if points else None,
           "normal": torch.empty(b, h, w, 3),
           "uv": torch.empty(b, h, w, 2)}
    job = _LayerJob(b=b, h=h, w=w, ids=ids.data_ptr(), eye=eye.data_ptr(),
                    dirs=dirs.data_ptr(), forward=forward.data_ptr(),
                    tv=tri_vertices.data_ptr(), tn=tri_normals.data_ptr(),
                    tuv=tri_uvs.data_ptr(), neighbors=tri_neighbors.data_ptr(),
                    back=int(back), tol=tol, keep_tol=keep_tol,
                    **{k: None if v is None else v.data_ptr() for k, v in out.items()})
    if not _call("layer", job):
        return None
    return out


@dataclass(frozen=True)
class SubTest:
    """What the sub-pixel flags read (csrc/subpixels.h): the n x n sub-pixel grid, the
    batch's triangles by global id (``meshes``, a MeshBatch: face normals, corners and
    their shading normals) and the fold test's tolerances (``subsamples``')."""

    n: int
    meshes: Any
    normal_tol: float
    face_tol: float


def _folds(test: SubTest) -> tuple[_Folds, list[torch.Tensor]] | None:
    """``Folds`` of ``test`` and the tensors it points into; None where one is not a
    float32 CPU tensor."""
    m = test.meshes
    keep = _inputs((m.face_normals, m.tri_vertices, m.tri_normals), ())
    if keep is None:
        return None
    return _Folds(face_normal=keep[0].data_ptr(), tv=keep[1].data_ptr(), tn=keep[2].data_ptr(),
                  normal_tol=test.normal_tol, face_tol=test.face_tol), keep


def raster_ids(vertices: torch.Tensor, faces: torch.Tensor, views: torch.Tensor,
               mvp: torch.Tensor, h: int, w: int, rows: tuple[int, int] | None = None,
               dtype: torch.dtype = torch.int64, sub: SubTest | None = None) -> tuple | None:
    """Both visibility layers of B views (csrc/raster.c): per pixel center, the nearest
    front-facing and the nearest back-facing triangle, as ``raster.visibility_pass`` draws
    them with OpenGL; ``None`` where the kernel is unavailable or an input is of another
    dtype or device (the caller then runs the OpenGL passes). With ``sub`` (int32 ids of
    a frame of whole pixels: h, w and the rows multiples of ``sub.n``) also the pixels'
    sub-pixel flags (B, rows / n, w / n) uint8 (csrc/subpixels.h), made as the ids are
    written: (front, back, flags).

    Args:
        vertices: (V, 3) float32 world positions of the views' meshes, concatenated.
        faces: (F, 3) int64 vertex indices, local to their mesh's vertex range.
        views: (B, 5) int64 per view: its mesh's vertex offset and count, face offset and
            count, and the offset added to the face index written (the batch's global id).
        mvp: (B, 4, 4) float64 ``P V`` per view (``raster.view_projection``).
        h, w: the frame (supersampled).
        rows: (r0, r1): only these rows of the frame (a strip of it: the same ids as the
            frame's rows there); None: all.

    Returns:
        front, back: (B, h, w) id offset + face index, -1 where no face is seen
        ((B, r1 - r0, w) with ``rows``), of ``dtype`` (int64, or int32: ids below 2^31).
    """
    if not available():
        return None
    keep = _inputs((vertices,), (faces, views))
    if (keep is None or mvp.dtype != torch.float64 or mvp.device.type != "cpu"
            or views.dim() != 2 or views.shape[1] != 5 or mvp.shape != (views.shape[0], 4, 4)):
        return None
    vertices, faces, views = keep
    mvp = as_input(mvp)
    b = views.shape[0]
    r0, r1 = (0, h) if rows is None else rows
    if not 0 <= r0 < r1 <= h:
        raise ValueError(f"raster_ids: rows {rows} are not a range of the frame's {h}")
    if dtype not in (torch.int64, torch.int32) or (
            dtype == torch.int32 and b and int(views[:, 4].max() + views[:, 3].max()) >= 2**31):
        return None
    front = torch.empty(b, r1 - r0, w, dtype=dtype)
    back = torch.empty(b, r1 - r0, w, dtype=dtype)
    job = _RasterJob(b=b, h=h, w=w, vertices=vertices.data_ptr(), faces=faces.data_ptr(),
                     views=views.data_ptr(), mvp=mvp.data_ptr(), front=front.data_ptr(),
                     back=back.data_ptr(), row0=r0, rows=r1 - r0,
                     ids32=int(dtype == torch.int32))
    if sub is not None:
        n, folds = sub.n, _folds(sub)
        if folds is None or dtype != torch.int32 or h % n or w % n or r0 % n or r1 % n:
            return None
        flags = torch.empty(b, (r1 - r0) // n, w // n, dtype=torch.uint8)
        job.sub_n, job.flags, job.folds = n, flags.data_ptr(), folds[0]
    if b and not _call("raster", job):
        return None
    return (front, back) if sub is None else (front, back, flags)


def sub_flags(ids: tuple[torch.Tensor, torch.Tensor], sub: SubTest) -> torch.Tensor | None:
    """The (B, h, w) uint8 sub-pixel flags (csrc/subpixels.h) of both layers' int32 ids on
    the (B, n h, n w) grid, drawn elsewhere than :func:`raster_ids` (which makes them as it
    draws); ``None`` where the kernel is unavailable or an input is of another dtype or
    device."""
    if not available():
        return None
    folds = _folds(sub)
    n = sub.n
    if folds is None or any(x.dtype != torch.int32 or x.device.type != "cpu" for x in ids):
        return None
    b, fh, fw = ids[0].shape
    if fh % n or fw % n:
        return None
    keep = [as_input(x) for x in ids]
    out = torch.empty(b, fh // n, fw // n, dtype=torch.uint8)
    job = _SubFlagsJob(b=b, h=fh // n, w=fw // n, n=n, front=keep[0].data_ptr(),
                       back=keep[1].data_ptr(), folds=folds[0], out=out.data_ptr())
    return out if _call("sub_flags", job) else None


def footprint(q: torch.Tensor, ok: torch.Tensor, center: torch.Tensor, proj: torch.Tensor,
              batch: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """``kernels.cone.footprint``: the screen footprint of the four bounding rays' exits, or
    ``None`` where the kernel is unavailable or an input is not a float32 / int64 / bool
    CPU tensor.

    Args:
        q: (N, 4, 3) the bounding rays' exits; ok: (N, 4) bool, found.
        center: (N, 3) the central ray's exit. proj: (B, 16)
            ``camera.projection_params`` per view; batch: (N,) int64 view per pixel.

    Returns:
        xy (N, 4, 2) the exits' pixel coordinates (the center's where ``ok`` is false),
        xy_c (N, 2) the center's, ext (N, 2) the bounding box's extent in x and y.
    """
    if not available():
        return None
    keep = _inputs((q, center, proj), (batch,), (ok,))
    if keep is None:
        return None
    q, center, proj, batch, ok = keep
    n = q.shape[0]
    xy, xy_c, ext = torch.empty(n, 4, 2), torch.empty(n, 2), torch.empty(n, 2)
    job = _FootprintJob(n=n, q=q.data_ptr(), ok=ok.data_ptr(), pc=center.data_ptr(),
                        proj=proj.data_ptr(), batch=batch.data_ptr(), xy=xy.data_ptr(),
                        xy_c=xy_c.data_ptr(), ext=ext.data_ptr())
    if n and not _call("footprint", job):
        return None
    return xy, xy_c, ext


def refract_x4(d: torch.Tensor, n: torch.Tensor, eta: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """csrc/optics.h's ``refract_x4`` (four rays at once, in lanes where built for them) and
    its scalar ``refract`` over the same rays, for the tests that hold the two to the same
    bits: ``d``, ``n`` (G, 4, 3) float32, ``eta`` (G,); ``None`` where the kernels do not
    run.

    Raises:
        ValueError: the shapes differ from those (the kernel reads 12 floats a group)."""
    g = d.shape[0] if d.dim() == 3 else -1
    if d.shape != (g, 4, 3) or n.shape != d.shape or eta.shape != (g,):
        raise ValueError(f"refract_x4: d and n must be (G, 4, 3) and eta (G,), got "
                         f"{tuple(d.shape)}, {tuple(n.shape)}, {tuple(eta.shape)}")
    if not available():
        return None
    keep = _inputs((d, n, eta), ())
    if keep is None:
        return None
    d, n, eta = keep
    lanes, scalar = torch.empty_like(d), torch.empty_like(d)
    job = _RefractX4Job(n=d.shape[0], d=d.data_ptr(), nrm=n.data_ptr(), eta=eta.data_ptr(),
                        lanes=lanes.data_ptr(), scalar=scalar.data_ptr())
    return (lanes, scalar) if _call("refract_x4", job) else None


def theta3(cs: torch.Tensor, eta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """csrc/sgtable.h's ``sg_theta_n`` and ``fresnel_n`` on a spread's three cosines (in
    lanes where built for them) and the scalar ``sg_theta`` and ``fresnel``, for the tests
    that hold them to the same bits: ``cs`` (G, 3) float32, ``eta`` (G,); each result
    (G, 2, 3): the table coordinates, then the reflectances. ``None`` where the kernels do
    not run."""
    if cs.dim() != 2 or cs.shape[1] != 3 or eta.shape != cs.shape[:1]:
        raise ValueError(f"theta3: cs must be (G, 3) and eta (G,), got {tuple(cs.shape)}, "
                         f"{tuple(eta.shape)}")
    keep = _inputs((cs, eta), ()) if available() else None
    if keep is None:
        return None
    cs, eta = keep
    lanes, scalar = torch.empty(cs.shape[0], 2, 3), torch.empty(cs.shape[0], 2, 3)
    job = _Theta3Job(n=cs.shape[0], cs=cs.data_ptr(), eta=eta.data_ptr(),
                     lanes=lanes.data_ptr(), scalar=scalar.data_ptr())
    return (lanes, scalar) if _call("theta3", job) else None


def views_in_range(batch: torch.Tensor, b: int) -> bool:
    """Whether every view index of ``batch`` lies in [0, b) (one reduction), so that a
    kernel reading per-view arrays by it never reads past them."""
    if batch.numel() == 0:
        return True
    lo, hi = torch.aminmax(batch)
    return int(lo) >= 0 and int(hi) < b


def _roughness_job(alpha: torch.Tensor, maps: tuple, ranges: torch.Tensor,
                   batch: torch.Tensor | None, uv: torch.Tensor, n: int):
    """The ``RoughnessJob`` of csrc/materials.c for n points (``batch``: their views, or
    None) and the tensors it points into (to keep), or None where the kernels do not run
    on them (unavailable, a gradient wanted, another dtype, shape or device)."""
    texs = [m for m in maps if m is not None]
    if (not available() or len(maps) != alpha.shape[0] or uv.shape != (n, 2)
            or ranges.shape != (len(maps), 2)
            or (batch is not None and (batch.dtype != torch.int64 or batch.shape != (n,)))
            or not no_grad_through(alpha, ranges, uv, *texs)
            or any(t.dtype != torch.float32 or t.dim() != 2 or min(t.shape) < 1
                   for t in texs)):
        return None
    keep = _inputs((alpha, ranges, uv, *texs), () if batch is None else (batch,))
    if keep is None:
        return None
    texs = iter(keep[3:3 + len(texs)])
    tex_of = [None if m is None else next(texs) for m in maps]
    ptrs = (ctypes.c_void_p * max(1, len(maps)))(
        *[None if t is None else t.data_ptr() for t in tex_of])
    hw = torch.tensor([(1, 1) if t is None else tuple(t.shape) for t in tex_of] or [(1, 1)],
                      dtype=torch.int64)
    job = _RoughnessJob(n=n, batch=keep[-1].data_ptr() if batch is not None else None,
                        uv=keep[2].data_ptr(), alpha=keep[0].data_ptr(),
                        maps=ctypes.cast(ptrs, ctypes.c_void_p), hw=hw.data_ptr(),
                        range=keep[1].data_ptr())
    return job, (keep, ptrs, hw)


def roughness_at(alpha: torch.Tensor, maps: tuple, ranges: torch.Tensor, batch: torch.Tensor,
                 uv: torch.Tensor) -> torch.Tensor | None:
    """``MaterialBatch.roughness_at`` in one call (csrc/materials.c, the tensor code's
    values): the roughness (N,) of points of views ``batch`` (N,) int64 at ``uv`` (N, 2),
    for views of uniform roughness ``alpha`` (B,), roughness ``maps`` (B (H, W) or None) and
    ``ranges`` (B, 2). ``None`` where the kernel does not run: unavailable, a gradient
    wanted, a tensor of another dtype, shape or device, or a view index outside [0, B)."""
    made = _roughness_job(alpha, maps, ranges, batch, uv, batch.shape[0])
    if made is None or not views_in_range(batch, len(maps)):  # (the tensor code raises)
        return None
    job, _keep = made
    out = torch.empty(batch.shape[0], dtype=torch.float32)
    job.out = out.data_ptr()
    return out if _call("roughness", job) else None


def level_coverage(alpha: torch.Tensor, maps: tuple, ranges: torch.Tensor, uv: torch.Tensor,
                   mask: torch.Tensor, levels: int) -> torch.Tensor | None:
    """``cone.level_coverage`` in one call (csrc/materials.c, the tensor code's values): per
    pixel of the back layer's ``uv`` (B, H, W, 2) and ``mask`` (B, H, W) its roughness as
    hat weights on ``levels`` levels, (B, H, W, levels); the materials as for
    :func:`roughness_at`. ``None`` where the kernel does not run."""
    b, h, w = mask.shape
    if (mask.dtype != torch.bool or mask.device.type != "cpu" or uv.shape != (b, h, w, 2)
            or levels < 1):
        return None
    made = _roughness_job(alpha, maps, ranges, None, uv.reshape(-1, 2), b * h * w)
    if made is None:
        return None
    job, _keep = made
    m = mask.contiguous()
    out = torch.empty((b, h, w, levels), dtype=torch.float32)
    cj = _CoverageJob(r=job, hw=h * w, levels=levels, mask=m.data_ptr(), out=out.data_ptr())
    return out if _call("level_coverage", cj) else None


def light_coverage(origin: torch.Tensor, direction: torch.Tensor, sharpness: torch.Tensor,
                   pos: torch.Tensor, radius: torch.Tensor, gl_x: torch.Tensor,
                   gl_w: torch.Tensor) -> torch.Tensor | None:
    """``lights.sg_light_coverage`` in one call (csrc/lighting.h's ``light_coverage``, the
    fused kernels' own): (N, L) float32 for lobes ``origin``, ``direction`` (N, 3),
    ``sharpness`` (N,) and their lights ``pos`` (N, L, 3), ``radius`` (N, L), on the
    Gauss-Legendre rule ``gl_x``, ``gl_w`` (float64). ``None`` where the kernel does not
    run: unavailable, a gradient wanted, or a tensor of another dtype, shape or device."""
    n = origin.shape[0]
    nl = radius.shape[1] if radius.dim() == 2 else -1
    if (not available() or origin.shape != (n, 3) or direction.shape != (n, 3)
            or sharpness.shape != (n,) or pos.shape != (n, nl, 3) or radius.shape != (n, nl)
            or gl_x.dtype != torch.float64 or gl_w.dtype != torch.float64
            or gl_x.shape != gl_w.shape or gl_x.dim() != 1
            or not no_grad_through(origin, direction, sharpness, pos, radius)):
        return None
    keep = _inputs((origin, direction, sharpness, pos, radius), ())
    if keep is None or gl_x.device.type != "cpu":
        return None
    o, d, k, p, r = keep
    gx, gw = gl_x.contiguous(), gl_w.contiguous()
    out = torch.empty((n, nl), dtype=torch.float32)
    job = _CoverJob(n=n, nl=nl, o=o.data_ptr(), d=d.data_ptr(), k=k.data_ptr(),
                    pos=p.data_ptr(), r=r.data_ptr(), gl_x=gx.data_ptr(), gl_w=gw.data_ptr(),
                    gl_n=gx.numel(), out=out.data_ptr())
    return out if _call("light_coverage", job) else None


def i0e(x: torch.Tensor) -> torch.Tensor | None:
    """csrc/lighting.h's ``i0e_n`` (torch.special.i0e as the light coverage evaluates it, 24
    values in lanes at a time) of the float64 CPU tensor ``x``, for the test that holds it to
    torch's; ``None`` where the kernels do not run or ``x`` is of another dtype or device."""
    if not available() or x.dtype != torch.float64 or x.device.type != "cpu":
        return None
    x = as_input(x)
    out = torch.empty_like(x)
    job = _I0eJob(n=x.numel(), x=x.data_ptr(), out=out.data_ptr())
    return out if _call("i0e", job) else None


def spread(p: torch.Tensor, n_c: torch.Tensor, dirs: torch.Tensor, n4: torch.Tensor,
           ok: torch.Tensor, ior: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor | None:
    """``kernels.cone.ray_spread``: the exit lobe's geometric variance from the four bounding
    rays refracted out at their exit normals, or ``None`` where the kernel is unavailable
    or an input is not a float32 / bool CPU tensor.

    Args:
        p, n_c: (N, 3) the central ray and its exit normal. dirs, n4: (N, 4, 3) the
            bounding rays and their exit normals; ok: (N, 4) bool, found.
        ior: (N,). fallback: (N,) the variance where none of the four found its exit.

    Returns:
        (N,) the variance.
    """
    if not available():
        return None
    keep = _inputs((p, n_c, dirs, n4, ior, fallback), (), (ok,))
    if keep is None:
        return None
    p, n_c, dirs, n4, ior, fallback, ok = keep
    n = p.shape[0]
    var, arg = torch.empty(n), torch.empty(n, 5)
    job = _SpreadJob(n=n, p=p.data_ptr(), n_c=n_c.data_ptr(), dirs=dirs.data_ptr(),
                     n4=n4.data_ptr(), ok=ok.data_ptr(), ior=ior.data_ptr(),
                     fallback=fallback.data_ptr(), two_ln4=2.0 * math.log(4.0), stage=0,
                     root_arg=arg.data_ptr(), var=var.data_ptr())
    if n == 0:
        return var
    if not _call("spread", job):
        return None
    # The refractions' square roots by torch, as optics.refract takes them (csrc/cone.c).
    root = torch.sqrt(arg)
    job.stage, job.root = 1, root.data_ptr()
    if not _call("spread", job):
        return None
    return var


def lattice_plan(front_mask: torch.Tensor, back_mask: torch.Tensor,
                 front_normal: torch.Tensor, back_normal: torch.Tensor,
                 back_depth: torch.Tensor, alpha: torch.Tensor, alpha_min: float,
                 normal_tol: float, depth_tol: float, stride: int = 1,
                 uniform: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """``adaptive._lattice_torch``'s (B, H/s, W/s) uint8 status and float32 gap of the
    layers' pixels of stride ``s`` (csrc/lattice.c; read in place, rounding up), and each
    view's counts (B, 2) int64 of object and waiting pixels (status > 0, status 2), or
    ``None`` where the kernel is unavailable or an input is not a float32 / bool CPU tensor.

    Args:
        front_mask, back_mask: (B, H, W). front_normal, back_normal: (B, H, W, 3).
        back_depth: (B, H, W). alpha: (B, H, W) or (B, 1, 1) front roughness.
        uniform: (B, H/s, W/s) bool, the pixels that may wait or be waited on (None: all).
    """
    made = _plan_layers(front_mask, back_mask, front_normal, back_normal, back_depth, alpha)
    if made is None:
        return None
    keep, fields = made
    b, fh, fw = front_mask.shape
    h, w = -(-fh // stride), -(-fw // stride)
    if uniform is not None:
        if uniform.shape != (b, h, w) or uniform.dtype != torch.bool or uniform.is_cuda:
            return None
        uniform = uniform.contiguous()
        keep.append(uniform)
        fields["uniform"] = uniform.data_ptr()
    status = torch.empty(b, h, w, dtype=torch.uint8)
    gap = torch.empty(b, h, w)
    counts = torch.zeros(b, 2, dtype=torch.int64)
    job = _LatticeJob(b=b, h=h, w=w, alpha_min=alpha_min, normal_tol=normal_tol,
                      depth_tol=depth_tol, rtol=0.0, radiance=None, status=status.data_ptr(),
                      gap=gap.data_ptr(), stride=stride, fh=fh, fw=fw,
                      counts=counts.data_ptr(), **fields)
    return (status, gap, counts) if _call("lattice_plan", job) else None


def _plan_layers(front_mask, back_mask, front_normal, back_normal, back_depth, alpha
                 ) -> tuple[list, dict] | None:
    """The layers a plan reads (:func:`lattice_plan`, :func:`uniform`) as job fields, with
    the contiguous tensors they point into; ``None`` where the kernels are unavailable or
    one is not a float32 / bool CPU tensor. ``alpha``: per sub-pixel or per view."""
    if not available():
        return None
    keep = _inputs((front_normal, back_normal, back_depth, alpha), (),
                   (front_mask, back_mask))
    if keep is None:
        return None
    per_pixel = int(alpha.numel() == front_mask.numel())
    return keep, dict(front_mask=keep[4].data_ptr(), back_mask=keep[5].data_ptr(),
                      front_normal=keep[0].data_ptr(), back_normal=keep[1].data_ptr(),
                      back_depth=keep[2].data_ptr(), alpha=keep[3].data_ptr(),
                      per_pixel=per_pixel)


def uniform(front_mask: torch.Tensor, back_mask: torch.Tensor, front_normal: torch.Tensor,
            back_normal: torch.Tensor, back_depth: torch.Tensor, alpha: torch.Tensor, n: int,
            smooth_alpha: float, normal_tol: float, depth_tol: float,
            region: torch.Tensor | None = None
            ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``adaptive.plan``'s (B, H/n, W/n) bool uniform pixels of the (B, H, W) sub-pixel
    layers and its (B, H, W) bool sub-pixels to shade (``region``: (B, H, W) bool or None;
    csrc/lattice.c), or ``None`` where the kernel is unavailable or an input is not a
    float32 / bool CPU tensor. ``alpha``: (B, H, W) or (B, 1, 1)."""
    b, fh, fw = front_mask.shape
    if (alpha.numel() not in (b, b * fh * fw) or fh % n or fw % n
            or (region is not None and (region.shape != front_mask.shape
                                        or region.dtype != torch.bool))):
        return None
    made = _plan_layers(front_mask, back_mask, front_normal, back_normal, back_depth, alpha)
    if made is None:
        return None
    out = torch.empty(b, fh // n, fw // n, dtype=torch.bool)
    shade = torch.empty(b, fh, fw, dtype=torch.bool)
    region = None if region is None else region.contiguous()  # held until the call returns
    job = _UniformJob(b=b, h=fh // n, w=fw // n, n=n, smooth_alpha=smooth_alpha,
                      normal_tol=normal_tol, depth_tol=depth_tol, uniform=out.data_ptr(),
                      region=None if region is None else region.data_ptr(),
                      shade=shade.data_ptr(), **made[1])
    return (out, shade) if _call("uniform", job) else None


def edges(front_mask: torch.Tensor, back_mask: torch.Tensor, front_normal: torch.Tensor,
          back_normal: torch.Tensor, back_depth: torch.Tensor, flags: torch.Tensor,
          alpha: torch.Tensor, normal_tol: float, depth_tol: float, smooth_alpha: float
          ) -> torch.Tensor | None:
    """``subsamples.edges``' (B, H, W) bool pixels of the one-sample layers (B, H, W) and
    their sub-pixel ``flags`` (B, H, W) uint8 (:func:`raster_ids`, :func:`sub_flags`)
    (csrc/lattice.c, the same decisions as the tensor code), or ``None`` where the kernel
    is unavailable or an input is not of its dtype on the CPU. ``alpha``: (B, H, W) or
    (B, 1, 1)."""
    b, h, w = front_mask.shape
    if alpha.numel() not in (b, b * h * w) or flags.shape != front_mask.shape:
        return None
    made = _plan_layers(front_mask, back_mask, front_normal, back_normal, back_depth, alpha)
    if made is None or flags.dtype != torch.uint8 or flags.device.type != "cpu":
        return None
    sub = as_input(flags)
    out = torch.empty(b, h, w, dtype=torch.bool)
    pairs = torch.empty(b, h, w, dtype=torch.uint8)
    job = _EdgesJob(b=b, h=h, w=w, sub=sub.data_ptr(), pairs=pairs.data_ptr(),
                    smooth_alpha=smooth_alpha, normal_tol=normal_tol, depth_tol=depth_tol,
                    edge=out.data_ptr(), **made[1])
    return out if _call("edges", job) else None


def refine(uniform: torch.Tensor, radiance: torch.Tensor, rtol: float) -> torch.Tensor | None:
    """``adaptive.refine``'s (B, H/n, W/n) bool pixels of ``uniform`` to shade at every
    sub-pixel, from the (B, H, W, 3) ``radiance`` (csrc/lattice.c, the same decisions as
    the tensor code), or ``None`` where the kernel is unavailable, a gradient is wanted or
    an input is not a float32 / bool CPU tensor."""
    b, h, w = uniform.shape
    if not available() or radiance.requires_grad or radiance.shape[1] % h or (
            radiance.shape[2] % w or radiance.shape[1] // h != radiance.shape[2] // w):
        return None
    keep = _inputs((radiance,), (), (uniform,))
    if keep is None:
        return None
    out = torch.empty(b, h, w, dtype=torch.bool)
    job = _RefineJob(b=b, h=h, w=w, n=radiance.shape[1] // h, uniform=keep[1].data_ptr(),
                     radiance=keep[0].data_ptr(), rtol=rtol, more=out.data_ptr())
    return out if _call("refine", job) else None


def box(x: torch.Tensor, n: int, mask: torch.Tensor | None = None,
        uniform: torch.Tensor | None = None) -> torch.Tensor | None:
    """``result.box`` (``mask`` None) or ``result.masked_box`` of ``x`` (B, H, W, C) over
    n x n blocks (n = 1: x where ``mask``, else 0), ``uniform`` (B, H/n, W/n) pixels taken
    as their first sub-pixel's value (``result.plan_box``), the same bits (csrc/box.c);
    ``None`` where the kernel is unavailable, a gradient is wanted, or an input is not a
    float32 / bool CPU tensor."""
    if not available() or x.dim() != 4 or x.requires_grad or (n == 1 and mask is None):
        return None
    if n == 2:  # the 2 x 2 filter is the many-buffer kernel's, with one buffer
        out = boxes([(x, 0 if mask is None else 1, uniform is not None)], (mask, None), uniform)
        return None if out is None else out[0]
    b, fh, fw, c = x.shape
    h, w = fh // n, fw // n
    if fh % n or fw % n or (mask is not None and mask.shape != (b, fh, fw)) or (
            uniform is not None and uniform.shape != (b, h, w)):
        return None
    keep = _inputs((x,), (), tuple(t for t in (mask, uniform) if t is not None))
    if keep is None:
        return None
    xs, rest = keep[0], keep[1:]
    m = rest.pop(0) if mask is not None else None
    u = rest.pop(0) if uniform is not None else None
    out = torch.empty(b, h, w, c)
    job = _BoxJob(b=b, h=h, w=w, n=n, c=c, x=xs.data_ptr(),
                  mask=None if m is None else m.data_ptr(),
                  uniform=None if u is None else u.data_ptr(), out=out.data_ptr())
    return out if _call("box", job) else None


def box_mips(x: torch.Tensor, max_levels: int) -> tuple[torch.Tensor, ...] | None:
    """``optics.ndf.build_box_mips`` of ``x`` (B, H, W, C) float32 in one call (csrc/box.c's
    ``mips``, the same bits): level 0 is ``x`` itself; ``None`` where the kernel is
    unavailable, a gradient is wanted, or ``x`` is not a float32 CPU tensor."""
    if not available() or x.dim() != 4 or x.requires_grad or max_levels < 1:
        return None
    keep = _inputs((x,), ())
    if keep is None:
        return None
    b, h, w, c = x.shape
    sizes = [(h, w)]
    while len(sizes) < max_levels and (h > 1 or w > 1):
        h, w = -(-h // 2), -(-w // 2)
        sizes.append((h, w))
    outs = [keep[0], *[torch.empty(b, hh, ww, c) for hh, ww in sizes[1:]]]
    if len(outs) == 1:
        return (x,)
    hw = torch.tensor(sizes, dtype=torch.int64)
    ptrs = (ctypes.c_void_p * len(outs))(*[o.data_ptr() for o in outs])
    job = _MipsJob(b=b, c=c, nlevels=len(outs), hw=hw.data_ptr(),
                   out=ctypes.cast(ptrs, ctypes.c_void_p), level=0)
    return (x, *outs[1:]) if _call("mips", job) else None


def _in_place(dtype: torch.dtype, *tensors: torch.Tensor) -> bool:
    """Whether every tensor is a contiguous CPU tensor of ``dtype``: what a kernel reads or
    writes where it lies, without a copy."""
    return all(x.dtype == dtype and x.is_contiguous() and x.device.type == "cpu"
               for x in tensors)


MASK_BLOCK = 16384
"""The elements a block of :func:`mask_index` counts and writes (a thread's unit)."""


def mask_index(mask: torch.Tensor, hw: int) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The flat indices of the set elements of a bool ``mask`` (any shape), in order, and
    each one's view (index // ``hw``): ``mask.reshape(-1).nonzero()`` and the division, by
    csrc/index.c in two sweeps on torch's threads. ``None`` where the kernels are
    unavailable or the mask is not a CPU bool tensor."""
    if not available() or mask.dtype != torch.bool or mask.device.type != "cpu" or hw < 1:
        return None
    m = mask.reshape(-1).contiguous()
    first = torch.empty(max(1, -(-m.numel() // MASK_BLOCK)), dtype=torch.int64)
    job = _MaskJob(n=m.numel(), hw=hw, block=MASK_BLOCK, mask=m.data_ptr(),
                   first=first.data_ptr())
    if not _call("mask_count", job):
        return None
    idx, view = torch.empty(job.total, dtype=torch.int64), torch.empty(job.total,
                                                                         dtype=torch.int64)
    job.idx, job.view = idx.data_ptr(), view.data_ptr()
    return (idx, view) if _call("mask_index", job) else None


def sample_slots(picked: torch.Tensor, ids: tuple[torch.Tensor, torch.Tensor], n: int
                 ) -> dict[str, torch.Tensor] | None:
    """``subsamples.gather``'s slots of the (B, h, w) bool ``picked`` pixels and their n x n
    samples on the (B, n h, n w) int32 rasterized ``ids`` (front, back), by csrc/index.c:
    ``pixels`` (B, K), the samples' ``rows`` and ``cols`` (B, K n n), both layers' ids
    there ``sid`` (2 x (B, K n n) int64, -1 past a view's pixels) and the taken samples'
    ``flat`` index in the ids and ``taken`` index in the slots (N n n); ``None`` where the
    kernels are unavailable or an input does not fit (the caller's tensor code runs)."""
    if (not available() or picked.dtype != torch.bool or picked.device.type != "cpu"
            or not _in_place(torch.int32, *ids)
            or any(x.shape != (picked.shape[0], n * picked.shape[1], n * picked.shape[2])
                   for x in ids)):
        return None
    b, h, w = picked.shape
    made = mask_index(picked, h * w)
    if made is None:
        return None
    idx, view = made
    count = torch.bincount(view, minlength=b)
    first = torch.cumsum(count, 0) - count
    k, nn = int(count.max()) if b else 0, n * n
    out = {"pixels": torch.empty(b, k, dtype=torch.int64),
           **{f: torch.empty(b, k * nn, dtype=torch.int64)
              for f in ("rows", "cols", "sid0", "sid1")},
           "flat": torch.empty(idx.numel() * nn, dtype=torch.int64),
           "taken": torch.empty(idx.numel() * nn, dtype=torch.int64)}
    job = _SlotsJob(b=b, h=h, w=w, n=n, k=k, idx=idx.data_ptr(), first=first.data_ptr(),
                    count=count.data_ptr(), ids0=ids[0].data_ptr(), ids1=ids[1].data_ptr(),
                    **{f: x.data_ptr() for f, x in out.items()})
    return out if _call("sample_slots", job) else None


def put_ids(ids: tuple[torch.Tensor, torch.Tensor], flat: torch.Tensor, taken: torch.Tensor,
            tri: tuple[torch.Tensor, torch.Tensor]) -> bool:
    """In place: ``ids[l].view(-1)[flat] = tri[l].view(-1)[taken]`` for both layers (int32,
    contiguous; :func:`sample_slots`' indices), by csrc/index.c; ``False``, nothing
    written, where the kernels are unavailable or the tensors do not fit."""
    if (not available() or not _in_place(torch.int32, *ids, *tri)
            or not _in_place(torch.int64, flat, taken) or taken.numel() != flat.numel()):
        return False
    job = _PutIdsJob(m=flat.numel(), flat=flat.data_ptr(), taken=taken.data_ptr(),
                     tri0=tri[0].data_ptr(), tri1=tri[1].data_ptr(), ids0=ids[0].data_ptr(),
                     ids1=ids[1].data_ptr())
    return _call("put_ids", job)


def clear_waiting(mask: torch.Tensor, status: torch.Tensor, stride: int) -> bool:
    """In place: ``mask[:, ::stride, ::stride] &= status != 2`` for a level's (B, h, w)
    uint8 ``status`` over the contiguous (B, H, W) bool ``mask`` (csrc/index.c); ``False``,
    nothing written, where the kernels are unavailable or the tensors do not fit."""
    b, fh, fw = mask.shape
    if (not available() or not _in_place(torch.bool, mask) or not _in_place(torch.uint8, status)
            or status.shape != (b, -(-fh // stride), -(-fw // stride))):
        return False
    _, h, w = status.shape
    job = _WaitJob(b=b, h=h, w=w, stride=stride, fh=fh, fw=fw, status=status.data_ptr(),
                   mask=mask.data_ptr())
    return _call("clear_waiting", job)


def one_sample_passes(front_mask: torch.Tensor, back_mask: torch.Tensor,
                      front_dist: torch.Tensor, back_dist: torch.Tensor,
                      rough: torch.Tensor, ior: torch.Tensor
                      ) -> tuple[torch.Tensor, ...] | None:
    """``result.pixel_passes``' buffers at one sample per pixel in one sweep (csrc/box.c's
    ``one_sample``, the tensor code's bits): the front coverage as 0 / 1, the thickness
    where both layers are covered, the roughness and the IOR times the coverage, each
    (B, H, W, 1). Masks and distances (B, H, W); ``rough`` (B, H, W, 1) or (B, 1, 1, 1);
    ``ior`` (B,). ``None`` where the kernel is unavailable, a gradient is wanted, or an
    input does not fit."""
    b, h, w = front_mask.shape
    per_pixel = rough.shape[1] != 1
    if (not available() or any(x.requires_grad for x in (front_dist, back_dist, rough, ior))
            or rough.numel() != (b * h * w if per_pixel else b) or ior.numel() != b):
        return None
    keep = _inputs((front_dist, back_dist, rough, ior), (), (front_mask, back_mask))
    if keep is None:
        return None
    fd, bd, r, i, fm, bm = keep
    out = torch.empty(4, b, h, w, 1)
    job = _OneSampleJob(n=b * h * w, hw=h * w, front_mask=fm.data_ptr(), back_mask=bm.data_ptr(),
                        front_dist=fd.data_ptr(), back_dist=bd.data_ptr(), rough=r.data_ptr(),
                        per_pixel=int(per_pixel), ior=i.data_ptr(),
                        coverage=out[0].data_ptr(), thickness=out[1].data_ptr(),
                        roughness=out[2].data_ptr(), ior_out=out[3].data_ptr())
    return tuple(out.unbind(0)) if _call("one_sample", job) else None


def put_rows(dst: torch.Tensor, pairs: list[tuple[torch.Tensor, torch.Tensor, int]]) -> bool:
    """For each ``(out, src, c)`` of ``pairs``, ``out``'s rows ``dst[s]`` := ``src``'s row
    s where ``dst[s] >= 0`` (csrc/box.c's ``put_rows``, in place): ``out`` (R rows of ``c``)
    and ``src`` (N rows of ``c``) float32 contiguous CPU tensors of any shape, read as rows
    of their last ``c`` values (no views made), ``dst`` (N,) int64. ``False`` (nothing
    written) where the kernel does not run: unavailable, a gradient wanted, or a tensor
    that does not fit."""
    n = dst.numel()
    if not (available() and _in_place(torch.int64, dst)) or not all(
            _in_place(torch.float32, o, x) and c > 0 and o.numel() % c == 0
            and x.numel() == n * c and not (o.requires_grad or x.requires_grad)
            for o, x, c in pairs):
        return False
    if n == 0 or not pairs:
        return True
    rows = min(o.numel() // c for o, _, c in pairs)
    if int(dst.max()) >= rows:
        raise IndexError(f"put_rows: a row {int(dst.max())} past the buffers' {rows}")
    outs = (ctypes.c_void_p * len(pairs))(*[o.data_ptr() for o, _, _ in pairs])
    srcs = (ctypes.c_void_p * len(pairs))(*[x.data_ptr() for _, x, _ in pairs])
    ch = torch.tensor([c for _, _, c in pairs], dtype=torch.int64)
    job = _PutRowsJob(n=n, nbuf=len(pairs), dst=dst.data_ptr(),
                      out=ctypes.cast(outs, ctypes.c_void_p),
                      src=ctypes.cast(srcs, ctypes.c_void_p), ch=ch.data_ptr())
    return _call("put_rows", job)


def boxes(items: list[tuple[torch.Tensor | None, int, bool]], masks: tuple, uniform
          ) -> list[torch.Tensor] | None:
    """Several 2 x 2 box filters of one supersampled frame in one pass (csrc/box.c's
    ``boxes``), each item's bits those :func:`box` gives it alone: ``(x, mask, uniform)``
    with x (B, 2h, 2w, C) float32 (None: the mask's coverage, (B, h, w, 1)), mask 0 (none),
    1 or 2 (``masks``' first or second, (B, 2h, 2w) bool) or 3 (both), and whether the
    ``uniform`` pixels (B, h, w) bool (or None) hold their first sub-pixel's value. ``None``
    where the kernel is unavailable, a gradient is wanted, or an input does not fit."""
    if not available() or not items:
        return None
    shape = next((m.shape for m in masks if m is not None), None)
    xs = [x for x, _, _ in items if x is not None]
    if shape is None and xs:
        shape = xs[0].shape[:3]
    if shape is None or shape[1] % 2 or shape[2] % 2:
        return None
    b, fh, fw = shape
    h, w = fh // 2, fw // 2
    if any(x.requires_grad or x.dim() != 4 or x.shape[:3] != shape for x in xs) or any(
            m is not None and m.shape != shape for m in masks) or (
            uniform is not None and uniform.shape != (b, h, w)):
        return None
    for x, mk, uni in items:
        if (mk in (1, 3) and masks[0] is None) or (mk in (2, 3) and masks[1] is None) or (
                uni and uniform is None) or (x is None and mk == 0):
            return None
    keep = _inputs(tuple(xs), (), tuple(m for m in (*masks, uniform) if m is not None))
    if keep is None:
        return None
    inputs, rest = keep[:len(xs)], keep[len(xs):]
    mptr = [rest.pop(0).data_ptr() if m is not None else None for m in masks]
    u = rest.pop(0) if uniform is not None else None
    outs, xp, it = [], [], iter(inputs)
    for x, _, _ in items:
        xi = next(it) if x is not None else None
        outs.append(torch.empty(b, h, w, 1 if xi is None else xi.shape[3]))
        xp.append(None if xi is None else xi.data_ptr())
    n = len(items)
    c = torch.tensor([o.shape[3] for o in outs], dtype=torch.int64)
    mask_of = torch.tensor([mk for _, mk, _ in items], dtype=torch.int64)
    use_u = torch.tensor([bool(uni) for _, _, uni in items], dtype=torch.uint8)
    x_arr, out_arr = (_p * n)(*xp), (_p * n)(*[o.data_ptr() for o in outs])  # (held here)
    job = _BoxesJob(b=b, h=h, w=w, nitems=n, masks=(_p * 2)(*mptr),
                    uniform=None if u is None else u.data_ptr(),
                    x=ctypes.cast(x_arr, _p), out=ctypes.cast(out_arr, _p),
                    c=c.data_ptr(), mask_of=mask_of.data_ptr(), use_uniform=use_u.data_ptr())
    done = _call("boxes", job)
    del keep, x_arr, out_arr
    return outs if done else None


def pixel_rays(frames: torch.Tensor, h: int, w: int, r0: int = 0, r1: int | None = None
               ) -> torch.Tensor | None:
    """``camera.pixel_rays_rows`` of every view at once (csrc/gbuffer.c, the same bits):
    ``frames`` (B, 11) float64 rows of forward, right, up, t and a, for an (h, w) grid; the
    (B, r1 - r0, w, 3) float32 rays of its rows [r0, r1) (default: all), or ``None`` where
    the kernel is unavailable."""
    if not available():
        return None
    r1 = h if r1 is None else r1
    fr = frames.to(torch.float64).contiguous()
    out = torch.empty(fr.shape[0], r1 - r0, w, 3)
    job = _RaysJob(b=fr.shape[0], h=h, w=w, r0=r0, rows=r1 - r0, frame=fr.data_ptr(),
                   out=out.data_ptr())
    return out if _call("pixel_rays", job) else None


def rays_at(frames: torch.Tensor, h: int, w: int, rows: torch.Tensor, cols: torch.Tensor
            ) -> torch.Tensor | None:
    """``camera.subpixel_rays`` (csrc/gbuffer.c, the same bits): ``frames`` (B, 11) as
    :func:`pixel_rays`' for an (h, w) grid, ``rows`` and ``cols`` (B, M) int64 -> the
    (B, M, 3) float32 rays through those (sub-)pixels, or ``None`` where the kernel is
    unavailable."""
    if (not available() or rows.dtype != torch.int64 or cols.dtype != torch.int64
            or rows.device.type != "cpu" or cols.device.type != "cpu"):
        return None
    fr = frames.to(torch.float64).contiguous()
    rows, cols = rows.contiguous(), cols.contiguous()
    b, m = rows.shape
    out = torch.empty(b, m, 3)
    job = _RaysAtJob(b=b, m=m, h=h, w=w, frame=fr.data_ptr(), rows=rows.data_ptr(),
                     cols=cols.data_ptr(), out=out.data_ptr())
    return out if _call("rays_at", job) else None


def center_samples(g, uniform: torch.Tensor, center_dirs: torch.Tensor) -> bool:
    """``adaptive._center_samples`` for every uniform pixel (B, H/n, W/n) of the
    supersampled G-buffer ``g``, in place on its front layer and rays (csrc/gbuffer.c);
    ``False`` (nothing written) where the kernel does not run: unavailable, a gradient
    wanted, or a tensor not a contiguous CPU one of its dtype."""
    f = g.front
    outs = (f.position, f.dist, f.depth, f.bary, f.normal, f.uv, g.ray_dir)
    ins = (center_dirs, g.eye, g.proj, g.meshes.tri_vertices, g.meshes.tri_normals,
           g.meshes.tri_uvs)
    ok = (available() and no_grad_through(*outs, *ins) and _in_place(torch.float32, *outs, *ins)
          and _in_place(torch.int32, f.tri) and _in_place(torch.bool, uniform))
    if not ok:
        return False
    b, h, w = uniform.shape
    job = _CenterJob(b=b, h=h, w=w, n=g.supersample, uniform=uniform.data_ptr(),
                     center_dirs=center_dirs.data_ptr(), eye=g.eye.data_ptr(),
                     proj=g.proj.data_ptr(), tv=g.meshes.tri_vertices.data_ptr(),
                     tn=g.meshes.tri_normals.data_ptr(), tuv=g.meshes.tri_uvs.data_ptr(),
                     tri=f.tri.data_ptr(), position=f.position.data_ptr(),
                     dist=f.dist.data_ptr(), depth=f.depth.data_ptr(), bary=f.bary.data_ptr(),
                     normal=f.normal.data_ptr(), uv=f.uv.data_ptr(),
                     ray_dir=g.ray_dir.data_ptr())
    return _call("center_samples", job)


def lattice_fill(status: torch.Tensor, gap: torch.Tensor, weight: torch.Tensor,
                 radiance: torch.Tensor, rtol: float, blend_from: float,
                 passes: list[torch.Tensor] = ()) -> bool:
    """``adaptive._fill_torch`` in place on ``status`` (B, H, W) uint8, ``weight`` (B, H, W)
    (written at status 5), ``radiance`` (B*H*W, 3) and each of ``passes`` (B*H*W, C)
    (float32, contiguous, on the CPU), with the plan's ``gap`` (B, H, W); ``False`` where
    the kernel did not run (nothing changed)."""
    arrays = (radiance, gap, weight, *passes)
    if not (available() and status.is_contiguous() and _in_place(torch.float32, *arrays)):
        return False
    b, h, w = status.shape
    ptrs = (ctypes.c_void_p * max(1, len(passes)))(*[x.data_ptr() for x in passes])
    chans = torch.tensor([x.shape[-1] for x in passes] or [0], dtype=torch.int64)
    job = _LatticeJob(b=b, h=h, w=w, rtol=rtol, radiance=radiance.data_ptr(),
                      status=status.data_ptr(), gap=gap.data_ptr(), weight=weight.data_ptr(),
                      blend_from=blend_from, npass=len(passes),
                      pass_ptr=ctypes.cast(ptrs, ctypes.c_void_p), pass_ch=chans.data_ptr())
    return _call("lattice_fill", job)


def _relight_job(n: int, row: torch.Tensor, sn: torch.Tensor, rot: torch.Tensor,
                 u0: torch.Tensor | None, view: torch.Tensor | None, u: torch.Tensor | None,
                 lobe: torch.Tensor | None, plain: bool, w_map: int, cols: int, last: int,
                 x0p1: torch.Tensor | None, w: torch.Tensor | None,
                 outs: list[torch.Tensor]) -> tuple[_RelightJob, list] | None:
    """A ``RelightJob`` for :func:`relight_reads` and :func:`relight_values` (its
    contiguous inputs kept alive in the list returned), or ``None`` where the kernel does
    not run: unavailable, a gradient wanted, an input of another dtype or device, ``outs``
    (written by the kernel) not contiguous CPU tensors."""
    shifted = u is None
    f32 = [sn, rot] + ([] if shifted else [u]) + ([] if plain else [x0p1, w])
    if not (available() and no_grad_through(*f32, *([u0] if shifted else []))):
        return None
    keep = _inputs(tuple(f32), ())
    ints = ([row] + ([u0] + ([] if view is None else [view]) if shifted else [lobe]))
    want = ([torch.int32] + ([torch.float64] + ([] if view is None else [torch.int64])
                             if shifted else [torch.int64]))
    if (keep is None or any(x is None or x.dtype != d or x.device.type != "cpu"
                            for x, d in zip(ints, want))
            or not all(x.is_contiguous() and x.device.type == "cpu" for x in outs)
            or row.shape != (n,) or sn.shape != (n, 2)):
        return None
    ints = [as_input(x) for x in ints]
    sn, rot = keep[0], keep[1]
    u = None if shifted else keep[2]
    x0p1, w = (None, None) if plain else keep[-2:]
    row = ints[0]
    u0, view = (ints[1], ints[2] if view is not None else None) if shifted else (None, None)
    lobe = None if shifted else ints[1]
    keep += ints

    def ptr(t):
        return None if t is None else t.data_ptr()

    job = _RelightJob(n=n, u0=ptr(u0), view=ptr(view), rot=rot.data_ptr(), nrot=rot.numel(),
                      u=ptr(u), lobe=ptr(lobe), plain=int(plain), w_map=w_map, cols=cols,
                      last=last, x0p1=ptr(x0p1), w=ptr(w), row=row.data_ptr(),
                      sn=sn.data_ptr())
    return job, keep


def relight_reads(idx: torch.Tensor, wts: torch.Tensor, row: torch.Tensor,
                  sn: torch.Tensor, rot: torch.Tensor, *, u0: torch.Tensor | None = None,
                  view: torch.Tensor | None = None, u: torch.Tensor | None = None,
                  lobe: torch.Tensor | None = None, plain: bool, w_map: int = 0, cols: int,
                  last: int, x0p1: torch.Tensor | None = None, w: torch.Tensor | None = None
                  ) -> bool:
    """``relight._Group.reads`` (csrc/relight.c): each lookup's u (``u0`` shifted by its
    view's rotation, or its lobe's given ``u``), column, four texel indices and weights,
    written into ``idx`` (n, 4) int32 and ``wts`` (n, 4) float32 (contiguous, CPU); the
    same values as the tensor code. ``False`` where the kernel did not run (unavailable,
    an input of another dtype or device, or a gradient wanted): nothing written, the
    caller runs its tensor code.

    Args:
        row: (n,) int32 upper row's first texel index. sn: (n, 2) the rows' weights.
        rot: (B,) float32 rotations (degrees). u0: (n,) float64 azimuth at rotation 0 and
            view: (n,) int64 (None: one view), for the shifted u; or u: (S,) float32 per
            lobe and lobe: (n,) int64.
        plain: ``envmap.lookup``'s grid on a map of width ``w_map``; else the SG level's
            ``x0p1``, ``w`` (n,) float32. cols: the image's columns; last: its last index.
    """
    n = row.shape[0]
    if (idx.dtype, wts.dtype) != (torch.int32, torch.float32) or \
            idx.shape != (n, 4) or wts.shape != (n, 4):
        return False
    made = _relight_job(n, row, sn, rot, u0, view, u, lobe, plain, w_map, cols, last, x0p1,
                        w, [idx, wts])
    if made is None:
        return False
    job, _keep = made
    job.idx, job.wts = idx.data_ptr(), wts.data_ptr()
    return n == 0 or _call("relight_reads", job)


def relight_values(vals: torch.Tensor, tex: torch.Tensor, row: torch.Tensor,
                   sn: torch.Tensor, rot: torch.Tensor, *, u0: torch.Tensor | None = None,
                   view: torch.Tensor | None = None, u: torch.Tensor | None = None,
                   lobe: torch.Tensor | None = None, plain: bool, w_map: int = 0, cols: int,
                   last: int, x0p1: torch.Tensor | None = None,
                   w: torch.Tensor | None = None) -> bool:
    """:func:`relight_reads` and the gather after it in one pass (csrc/relight.c): each
    lookup's value, the weighted sum of its four texels of ``tex`` (T, 3) float32 as
    ``F.embedding_bag`` (mode sum, per-sample weights) sums them, written into ``vals``
    (n, 3) float32 (contiguous, CPU); nothing kept per rotation. ``False`` where the
    kernel did not run (as :func:`relight_reads`; also where an index falls outside the
    image, a NaN u, where ``embedding_bag`` raises): the caller runs its tensor code.
    Other arguments as :func:`relight_reads`' (``last`` < T)."""
    n = row.shape[0]
    if (vals.dtype != torch.float32 or vals.shape != (n, 3) or tex.dtype != torch.float32
            or tex.dim() != 2 or tex.shape[1] != 3 or not 0 <= last < tex.shape[0]
            or tex.requires_grad and torch.is_grad_enabled()):
        return False
    made = _relight_job(n, row, sn, rot, u0, view, u, lobe, plain, w_map, cols, last, x0p1,
                        w, [vals, tex])
    if made is None:
        return False
    job, _keep = made
    status = torch.zeros(1, dtype=torch.int32)
    job.tex, job.vals, job.status = tex.data_ptr(), vals.data_ptr(), status.data_ptr()
    return n == 0 or (_call("relight_reads", job) and int(status) == 0)


__all__ = ["as_input", "available", "boxes", "build", "footprint", "lattice_fill",
           "lattice_plan", "layer", "library_path", "march", "native_enabled",
           "no_grad_through", "raster_ids", "refract_x4", "relight_reads", "relight_values",
           "set_native", "spread", "views_in_range"]
