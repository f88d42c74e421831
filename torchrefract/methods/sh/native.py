"""The native twins of :func:`.shade.evaluate` (``csrc/sh_eval.c``) and of the
precomputation's :func:`.paths.trace_paths` (``csrc/sh_paths.c``), built on first use into
one library.

Eq. 2's evaluation is 3 samples x E view directions x 45 coefficients x C channels per
pixel: in eager torch a chain of gathers and small matrix products over 10^6-10^7-element
temporaries (memory-bound, ~80% of ``sh``'s frame time before this kernel); the C kernel
evaluates one pixel's SH in registers and cache. It is used where no gradient is wanted
through the view directions (:func:`torchrefract.kernels.native.no_grad_through`) and the
package's native kernels are enabled (``RenderSettings(native=...)``); elsewhere, or where
the build fails (a warning, once), the tensor code runs: the same values to float32
rounding (the sums run in another order; tests/test_sh.py).

The path kernel follows each path to its end with Embree called from C (the scene of
:class:`.tracer.EmbreeNative`, ``rtcIntersect16`` packets), in blocks of live rays kept
compact, with the tensor code's float operations in its order and torch's own square root
(:func:`torch_sqrt_function`): its path ends, and so the tables, are bit-equal to the
tensor code's on embreex (tests/test_sh.py), ~3-4x faster where the tensor path step
dominated (teapot) and Embree-bound elsewhere (docs/decisions_sh.md).

The fused shading (``csrc/sh_shade.c``, :func:`shade_job`) does the whole of
:func:`.shade.render_sh` per pixel on the package kernels' frame
(``kernels/csrc/frame.h``: the table lobes and lookups written once, there), calling the
map of ``csrc/sh_eval.c`` per block of pixels.

Built by :func:`torchrefract.kernels.native.build` (its compiler, flags, CPU key and thread
split, ``csrc/common.h``) into the same cache folder, as its own small library, with
``-O3 -march=native`` where the compiler takes it and ``-ffp-contract=off`` (no
contracted multiply-adds: the path kernel claims bit equality; eq. 2's kernel sums in
another order and claims float32 rounding).
"""

from __future__ import annotations

import ctypes
import threading
import warnings
from pathlib import Path

import torch

from torchrefract import settings
from torchrefract.kernels import native as _native

SOURCE = Path(__file__).with_name("csrc") / "sh_eval.c"
SOURCES = (SOURCE, SOURCE.with_name("sh_paths.c"), SOURCE.with_name("sh_shade.c"))
"""Compiled together into one library: eq. 2's evaluation, the precomputation's paths and
the fused shading (which includes the package kernels' headers: frame.h and its own)."""
HEADERS = (SOURCE.with_name("sh_jobs.h"), *_native.HEADERS)
CPAD = 8
"""Channels per coefficient in the kernel's table (the 6 stored, zero-padded to a vector)."""
MAX_DIRECTIONS = 5
MAP_CHANNELS = 7
"""The channels :func:`map_pixels` reads (``precompute.CHANNELS``: exit direction, length,
exit cosine, throughput, gain)."""

_p = ctypes.c_void_p


class _ShEvalJob(ctypes.Structure):
    """ctypes mirror of ``ShEvalJob`` in csrc/sh_eval.c."""

    _fields_ = [("n", ctypes.c_int64), ("e", ctypes.c_int64), ("order", ctypes.c_int64),
                ("c", ctypes.c_int64), ("c_rest", ctypes.c_int64), ("omega", _p),
                ("samples", _p), ("s_w", _p), ("faces", _p), ("bary", _p), ("lattice", _p),
                ("rate", ctypes.c_int64), ("spread", _p), ("frame", _p), ("coeffs", _p),
                ("weights", _p), ("out", _p)]


class _ShMapJob(ctypes.Structure):
    """ctypes mirror of ``ShMapJob`` in csrc/sh_eval.c."""

    _fields_ = [("eval", _ShEvalJob), ("n", ctypes.c_int64), ("sel", _p), ("pix", _p),
                ("item", _p), ("tri", _p), ("gbary", _p), ("face_offset", _p), ("view", _p),
                ("var_view", _p), ("alpha", _p), ("rotation", _p), ("scale", _p),
                ("rough", _p), ("radius", ctypes.c_float), ("max_spread", ctypes.c_float),
                ("direction", _p), ("length", _p), ("cos_exit", _p), ("throughput", _p),
                ("var_geo", _p)]


class _ShShadeJob(ctypes.Structure):
    """ctypes mirror of ``ShShadeJob`` in csrc/sh_shade.c."""

    _fields_ = [("f", _native._Frame), ("maps", _p), ("branches", _p), ("table_of", _p),
                ("ntables", ctypes.c_int64), ("two", ctypes.c_int), ("conserve", ctypes.c_int),
                ("lobe_sigma", _p), ("path_length", _p), ("shared", _p)]


class _ShPathJob(ctypes.Structure):
    """ctypes mirror of ``ShPathJob`` in csrc/sh_paths.c."""

    _fields_ = [("n", ctypes.c_int64), ("max_events", ctypes.c_int64),
                ("greedy", ctypes.c_int64), ("ior", ctypes.c_float), ("inv_ior", ctypes.c_float),
                ("eps", ctypes.c_float), ("pad0", ctypes.c_float), ("p", _p), ("nrm", _p),
                ("omega", _p), ("tri_n", _p), ("g_n", _p), ("scene", _p), ("intersect1", _p),
                ("intersect16", _p), ("vsqrt", _p), ("direction", _p), ("length", _p),
                ("cos_exit", _p), ("throughput", _p), ("events", _p),
                ("branches", ctypes.c_int64), ("b_direction", _p), ("b_length", _p),
                ("b_cos_exit", _p), ("b_throughput", _p), ("b_events", _p), ("b_split", _p),
                ("gain", _p), ("b_gain", _p)]


_LOCK = threading.Lock()
_LIB: ctypes.CDLL | None = None
_FAILED: str | None = None


def library_path() -> Path:
    """Where the built kernels live for these sources, flags and platform."""
    return _native.library_path(name="sh", sources=SOURCES, headers=HEADERS)


def build() -> Path:
    """Compile the kernels into the cache (if not there yet), as the package's own
    (:func:`torchrefract.kernels.native.build`: the same compiler, flags and fallbacks).

    Raises:
        RuntimeError: no C compiler, or the compile failed (its output quoted).
    """
    return _native.build(name="sh", sources=SOURCES, headers=HEADERS)


def _load() -> ctypes.CDLL | None:
    global _LIB, _FAILED
    if _LIB is not None or _FAILED is not None:
        return _LIB
    with _LOCK:
        if _LIB is None and _FAILED is None:
            try:
                lib = ctypes.CDLL(str(build()))
                _native.bind(lib, {"sh_eval": _ShEvalJob, "sh_map": _ShMapJob,
                                   "sh_paths": _ShPathJob, "sh_shade": _ShShadeJob})
                lib.torchrefract_sh_eval_half.restype = ctypes.c_int
                _LIB = lib
            except Exception as exc:  # noqa: BLE001  (any build or load failure: fall back)
                _FAILED = f"{type(exc).__name__}: {exc}"
                warnings.warn(f"torchrefract: the native sh kernel is unavailable, using the "
                              f"tensor code (same images, slower): {_FAILED}", RuntimeWarning,
                              stacklevel=3)
    return _LIB


def available() -> bool:
    """Whether the kernel runs now: native kernels enabled, built and loaded."""
    return settings.current().native and _load() is not None


def table_half() -> bool:
    """Whether the built kernel reads the table as float16 (F16C: the stored values, half
    the bytes) rather than float32."""
    return _load() is not None and bool(_LIB.torchrefract_sh_eval_half())


def padded_coeffs(coeffs: torch.Tensor, half: bool | None = None) -> torch.Tensor:
    """(S, 45, C) float16 table -> (S, 45, :data:`CPAD`), channels zero-padded (the
    kernel's layout: the channels of one coefficient side by side), float16 where the
    kernel reads it so (``half``; None: :func:`table_half`), else float32."""
    s, k, c = coeffs.shape
    if k != 45 or c > CPAD:
        raise ValueError(f"sh table of shape {tuple(coeffs.shape)}: expected (S, 45, <= {CPAD})")
    half = table_half() if half is None else half
    out = torch.zeros(s, k, CPAD, dtype=torch.float16 if half else torch.float32)
    out[:, :, :c] = coeffs.to(out.dtype)
    return out


def _run(padded: torch.Tensor, frame: torch.Tensor, omega: torch.Tensor, e: int, order: int,
         weights: torch.Tensor, channels: int, rest_channels: int, **inputs
         ) -> torch.Tensor | None:
    """Fill the job (``inputs``: its other fields, tensors or plain values) and run it."""
    if not (1 <= e <= MAX_DIRECTIONS and 1 <= channels <= CPAD
            and 0 <= rest_channels <= channels) or _load() is None:
        return None
    if (padded.dtype == torch.float16) != table_half() or tuple(padded.shape[1:]) != (45, CPAD):
        return None
    n = omega.shape[0]
    out = torch.empty(n, e, channels)
    if n == 0:
        return out
    # contiguous copies held here until the call returns
    held = {k: v.contiguous() if isinstance(v, torch.Tensor) else v for k, v in inputs.items()}
    held.update(omega=omega.detach().float().contiguous(), frame=frame.contiguous(),
                weights=weights.detach().float().contiguous(), coeffs=padded.contiguous())
    job = _ShEvalJob(n=n, e=e, order=order, c=channels, c_rest=rest_channels,
                     out=out.data_ptr(),
                     **{k: v.data_ptr() if isinstance(v, torch.Tensor) else v
                        for k, v in held.items()})
    if _LIB.torchrefract_sh_eval(ctypes.byref(job), torch.get_num_threads()) != 0:
        return None
    return out


def evaluate(padded: torch.Tensor, frame: torch.Tensor, samples: torch.Tensor,
             s_w: torch.Tensor, omega: torch.Tensor, order: int, weights: torch.Tensor,
             channels: int, rest_channels: int) -> torch.Tensor | None:
    """The kernel's eq. 2 (the arguments of :func:`.shade.evaluate_samples`): None where
    it cannot run (the caller runs the tensor code).

    Args:
        padded: (S, 45, CPAD) from :func:`padded_coeffs`; frame: (S, 3, 3).
        samples: (N, 3) int64; s_w: (N, 3) float32; omega: (N, E, 3), E <= 5.
        order: highest band; weights: (K,) window.
        channels: the first ``channels`` of the table for direction 0;
        rest_channels: for directions 1.. (the others 0).

    Returns:
        (N, E, channels) float32.
    """
    return _run(padded, frame, omega, omega.shape[1], order, weights, channels, rest_channels,
                samples=samples, s_w=s_w.detach().float())


def evaluate_points(padded: torch.Tensor, frame: torch.Tensor, lattice: torch.Tensor,
                    rate: int, faces: torch.Tensor, bary: torch.Tensor, omega: torch.Tensor,
                    spread: torch.Tensor | None, order: int, weights: torch.Tensor,
                    channels: int, rest_channels: int) -> torch.Tensor | None:
    """:func:`evaluate` with the samples found here (``layout.interpolation`` of ``faces``
    (N,) and ``bary`` (N, 3) on ``lattice`` (F, P) at ``rate``) and, with ``spread`` (N,),
    the view directions too: ``omega`` (N, 3), then the four at angle ``spread`` around it
    (``shade._map_pixels``); without, ``omega`` is (N, 3) alone. Returns (N, E, channels)
    with E = 5 or 1, or None."""
    return _run(padded, frame, omega, 1 if spread is None else MAX_DIRECTIONS, order, weights,
                channels, rest_channels, faces=faces, bary=bary.detach().float(),
                lattice=lattice, rate=int(rate),
                spread=None if spread is None else spread.detach().float())


def _f32(x: float) -> float:
    """A scalar rounded to float32 as torch rounds a Python float against float32 tensors
    (the kernels' float fields)."""
    return float(torch.tensor(x, dtype=torch.float32))


def _suits(coeffs: torch.Tensor) -> bool:
    """Whether a padded table (:func:`padded_coeffs`) is in the layout the built kernel
    reads."""
    return (tuple(coeffs.shape[1:]) == (45, CPAD)
            and (coeffs.dtype == torch.float16) == table_half())


def _map_job(coeffs: torch.Tensor, frame: torch.Tensor, lattice: torch.Tensor, rate: int,
             order: int, weights: torch.Tensor, radius: float, max_spread: float,
             items: dict[str, torch.Tensor], tri: torch.Tensor, bary: torch.Tensor,
             keep: list) -> _ShMapJob:
    """A ``ShMapJob``'s table, window, items' poses (``face_offset``, ``rotation``,
    ``scale``) and the G-buffer's front faces and barycentrics; its positions, per-pixel
    arrays, ``rough`` and outputs left unset. The tensors it points into go to ``keep``."""
    held = {"coeffs": coeffs.contiguous(), "frame": frame.float().contiguous(),
            "lattice": lattice.long().contiguous(),
            "weights": weights.detach().float().contiguous(),
            "face_offset": items["face_offset"].long().contiguous(),
            "rotation": items["rotation"].float().contiguous(),
            "scale": items["scale"].float().contiguous(),
            "tri": tri.to(torch.int32).contiguous(), "gbary": bary.float().contiguous()}
    keep.extend(held.values())
    ev = _ShEvalJob(n=0, e=1, order=int(order), c=MAP_CHANNELS, c_rest=3, rate=int(rate),
                    **{k: held[k].data_ptr() for k in ("coeffs", "frame", "lattice",
                                                         "weights")})
    return _ShMapJob(eval=ev, radius=_f32(radius), max_spread=_f32(max_spread),
                     **{k: held[k].data_ptr() for k in ("tri", "gbary", "face_offset",
                                                          "rotation", "scale")})


def map_pixels(padded: torch.Tensor, frame: torch.Tensor, lattice: torch.Tensor, rate: int,
               order: int, weights: torch.Tensor, radius: float, max_spread: float,
               sel: torch.Tensor, pixels: dict[str, torch.Tensor], items: dict[str, torch.Tensor],
               out: dict[str, torch.Tensor]) -> bool:
    """:func:`.shade._map_pixels` for the positions ``sel`` of the object pixels (their
    items sharing the table ``padded``, ``frame``, ``lattice``, ``rate``): writes
    ``out``'s ``direction`` (N, 3), ``length``, ``cos_exit``, ``throughput`` and ``var_geo``
    (N,) at ``sel``; False where the kernel cannot run (the caller runs the tensor code).

    Args:
        pixels: per object pixel ``pix`` (flat G-buffer index), ``item``, ``view`` (N, 3),
            ``var_view``, ``alpha``; and ``tri``, ``bary``: the G-buffer's front faces
            (batch ids, int32) and barycentrics, flat.
        items: per batch item ``face_offset``, ``rotation`` (B, 3, 3), ``scale`` (B,) and
            ``rough`` (B,) bool: whether its four offset views are read.
    """
    if _load() is None or padded.shape[-1] != CPAD or not _suits(padded) or not all(
            out[k].is_contiguous() and out[k].dtype == torch.float32 for k in out):
        return False
    n = int(sel.numel())
    if n == 0:
        return True
    keep: list = []
    job = _map_job(padded, frame, lattice, rate, order, weights, radius, max_spread, items,
                   pixels["tri"], pixels["bary"], keep)
    held = {"sel": sel.long().contiguous(), "pix": pixels["pix"].long().contiguous(),
            "item": pixels["item"].long().contiguous(),
            "view": pixels["view"].detach().float().contiguous(),
            "var_view": pixels["var_view"].detach().float().contiguous(),
            "alpha": pixels["alpha"].detach().float().contiguous(),
            "rough": items["rough"].to(torch.uint8).contiguous()}
    job.n = n
    for k, v in held.items():
        setattr(job, k, v.data_ptr())
    for k in ("direction", "length", "cos_exit", "throughput", "var_geo"):
        setattr(job, k, out[k].data_ptr())
    return _LIB.torchrefract_sh_map(ctypes.byref(job), torch.get_num_threads()) == 0


def library() -> ctypes.CDLL | None:
    """The loaded library (its fused shading's entry for ``shading.fused._run``), or None
    where it is unavailable."""
    return _load()


def shade_job(frame, tables: list[dict], table_of: torch.Tensor, order: int,
              weights: torch.Tensor, max_spread: float, items: dict[str, torch.Tensor],
              front: dict[str, torch.Tensor], two: bool, conserve: bool,
              passes: dict[str, torch.Tensor], keep: list) -> "_ShShadeJob | None":
    """The job of csrc/sh_shade.c's fused shading over ``frame`` (``shading.fused._frame``'s,
    without the march): per table of the batch its ``padded`` coefficients (as
    :func:`map_pixels`'), with ``two`` its ``branch``'s (the reflected branch's channels),
    and its layout's ``frame``, ``lattice``, ``rate`` and ``radius``; ``table_of`` (B,) each
    view's table; ``items`` (as :func:`map_pixels`', but for ``rough``: the kernel decides
    it per pass from its pixels, as the tensor code), the G-buffer's ``front`` faces
    ``tri`` (int32) and barycentrics ``bary``, the exit rule and the ``lobe_sigma`` and
    ``path_length`` passes (B*H*W float32, written in place); the tensors it points into
    appended to ``keep``. None where the kernel cannot run."""
    coeffs = [t["padded"] for t in tables] + ([t["branch"] for t in tables] if two else [])
    if _load() is None or order > 8 or not tables or not all(_suits(c) for c in coeffs):
        return None

    def maps(key: str):
        """The C array of each table's ``ShMapJob`` over its ``key`` coefficients."""
        made = (_ShMapJob * len(tables))(*[
            _map_job(t[key], t["frame"], t["lattice"], t["rate"], order, weights, t["radius"],
                     max_spread, items, front["tri"], front["bary"], keep) for t in tables])
        keep.append(made)
        return ctypes.cast(made, _p)

    table_of = table_of.long().contiguous()
    keep.append(table_of)
    return _ShShadeJob(f=frame, maps=maps("padded"), branches=maps("branch") if two else None,
                       table_of=table_of.data_ptr(), ntables=len(tables), two=int(two),
                       conserve=int(conserve), lobe_sigma=passes["lobe_sigma"].data_ptr(),
                       path_length=passes["path_length"].data_ptr())


_VSQRT: list = []


def torch_sqrt_function() -> int | None:
    """The address of the function behind ``torch.sqrt`` on float32 CPU tensors where it
    is not the correctly rounded square root: MKL's ``vsSqrt`` (exported by libtorch_cpu
    where torch is built with MKL; ~20% of its values are one ulp from sqrtf), checked on
    100k values; None where torch.sqrt is sqrtf (the kernel's own) or neither matches
    (then the paths agree with the tensor code to float32 rounding, not bit for bit)."""
    if _VSQRT:
        return _VSQRT[0]
    x = torch.rand(100_000, generator=torch.Generator().manual_seed(0)) * 4.0
    ref = x.sqrt()
    found = None
    if not torch.equal(ref, x.double().sqrt().float()):
        lib_dir = Path(torch.__file__).parent / "lib"
        for name in ("libtorch_cpu.so", "libtorch_cpu.dylib"):
            try:
                fn = ctypes.CDLL(str(lib_dir / name)).vsSqrt
            except (OSError, AttributeError):
                continue
            fn.argtypes, fn.restype = [ctypes.c_int, _p, _p], None
            out = torch.empty_like(x)
            fn(x.numel(), x.data_ptr(), out.data_ptr())
            if torch.equal(out, ref):
                found = ctypes.cast(fn, _p).value
            break
    _VSQRT.append(found)
    return found


def trace_paths(embree, tri_normals: torch.Tensor, g_normals: torch.Tensor, p: torch.Tensor,
                n: torch.Tensor, omega: torch.Tensor, ior: float, max_events: int, eps: float,
                branch: str, threads: int = 1, packets: bool = True, branches: int = 1):
    """:func:`.paths.trace_paths` in C (``csrc/sh_paths.c``) on a :class:`.tracer.EmbreeNative`
    scene: the same :class:`.paths.PathEnds`, bit for bit (tests/test_sh.py), or None where
    the library is unavailable (the caller runs the tensor code).

    Args:
        embree: the mesh's :class:`.tracer.EmbreeNative`.
        tri_normals: (F, 3, 3) unit shading normals at the corners.
        g_normals: (F, 3) unit geometric normals, as :func:`.paths.geometric_normals`.
        p, n, omega: (P, 3) entry points, outward normals, directions to the viewer.
        ior, max_events, eps, branch, branches: as :func:`.paths.trace_paths`.
        threads: threads of the call (1 where the caller runs chunks in threads).
        packets: cast 16 rays per Embree call (``rtcIntersect16``), else one by one.
    """
    from torchrefract.methods.sh.paths import PathEnds  # noqa: PLC0415 (cycle)

    if _load() is None:
        return None
    count = p.shape[0]
    out = {"direction": torch.empty(count, 3), "length": torch.empty(count),
           "cos_exit": torch.empty(count), "throughput": torch.empty(count),
           "events": torch.empty(count, dtype=torch.int64), "gain": torch.empty(count)}
    fork = {"b_direction": torch.empty(count, 3), "b_length": torch.empty(count),
            "b_cos_exit": torch.empty(count), "b_throughput": torch.empty(count),
            "b_events": torch.zeros(count, dtype=torch.int64),
            "b_split": torch.zeros(count, dtype=torch.uint8), "b_gain": torch.empty(count)}
    two = int(branches) == 2
    held = {"p": p.float().contiguous(), "nrm": n.float().contiguous(),
            "omega": omega.float().contiguous(), "tri_n": tri_normals.float().contiguous(),
            "g_n": g_normals.float().contiguous()}
    job = _ShPathJob(n=count, max_events=int(max_events), greedy=int(branch == "greedy"),
                     ior=_f32(ior), inv_ior=_f32(1.0 / ior), eps=_f32(eps), pad0=0.0,
                     scene=embree.scene, intersect1=embree.intersect1,
                     intersect16=embree.intersect16 if packets else None,
                     vsqrt=torch_sqrt_function(), branches=2 if two else 1,
                     **{k: v.data_ptr() for k, v in {**held, **out}.items()},
                     **{k: v.data_ptr() if two else None for k, v in fork.items()})
    if _LIB.torchrefract_sh_paths(ctypes.byref(job), max(1, int(threads))) != 0:
        return None
    if not two:
        return PathEnds(**out)
    split = fork["b_split"].bool()
    s1 = split[:, None]
    branch_ends = PathEnds(
        direction=torch.where(s1, fork["b_direction"], out["direction"]),
        length=torch.where(split, fork["b_length"], out["length"]),
        cos_exit=torch.where(split, fork["b_cos_exit"], out["cos_exit"]),
        throughput=torch.where(split, fork["b_throughput"], 0.0),
        events=fork["b_events"], gain=torch.where(split, fork["b_gain"], out["gain"]))
    return PathEnds(**out, branch=branch_ends)


__all__ = ["CPAD", "MAP_CHANNELS", "SOURCES", "available", "build", "evaluate",
           "evaluate_points", "library", "library_path", "map_pixels", "padded_coeffs",
           "shade_job", "table_half",
           "torch_sqrt_function", "trace_paths"]
