"""The native twin of :func:`.shade.evaluate` (``csrc/sh_eval.c``), built on first use.

Eq. 2's evaluation is 3 samples x E view directions x 45 coefficients x C channels per
pixel: in eager torch a chain of gathers and small matrix products over 10^6-10^7-element
temporaries (memory-bound, ~80% of ``sh``'s frame time before this kernel); the C kernel
evaluates one pixel's SH in registers and cache. It is used where no gradient is wanted
through the view directions (:func:`torchrefract.kernels.native.no_grad_through`) and the
package's native kernels are enabled (``RenderSettings(native=...)``); elsewhere, or where
the build fails (a warning, once), the tensor code runs: the same values to float32
rounding (the sums run in another order; tests/test_sh.py).

Built like :mod:`torchrefract.kernels.native` (its compiler lookup, CPU key and thread
split, ``csrc/common.h``) into the same cache folder, as its own small library, with
``-O3 -march=native`` where the compiler takes it (contracted multiply-adds allowed: the
kernel does not claim bit equality, only float32 rounding).
"""

from __future__ import annotations

import ctypes
import hashlib
import platform
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import torch

from torchrefract import settings
from torchrefract.kernels import native as _native
from torchrefract.output.atomic import atomic_path

SOURCE = Path(__file__).with_name("csrc") / "sh_eval.c"
HEADER = Path(_native.__file__).with_name("csrc") / "common.h"
FLAGS = ("-O3", "-shared", "-fPIC", "-pthread", "-ffp-contract=off", "-fno-fast-math")
CPAD = 8
"""Channels per coefficient in the kernel's table (the 6 stored, zero-padded to a vector)."""
MAX_DIRECTIONS = 5

_p = ctypes.c_void_p


class _ShEvalJob(ctypes.Structure):
    """ctypes mirror of ``ShEvalJob`` in csrc/sh_eval.c."""

    _fields_ = [("n", ctypes.c_int64), ("e", ctypes.c_int64), ("order", ctypes.c_int64),
                ("c", ctypes.c_int64), ("c_rest", ctypes.c_int64), ("omega", _p),
                ("samples", _p), ("s_w", _p), ("faces", _p), ("bary", _p), ("lattice", _p),
                ("rate", ctypes.c_int64), ("spread", _p), ("frame", _p), ("coeffs", _p),
                ("weights", _p), ("out", _p)]


_LOCK = threading.Lock()
_LIB: ctypes.CDLL | None = None
_FAILED: str | None = None


def library_path() -> Path:
    """Where the built kernel lives for this source, flags and platform."""
    h = hashlib.sha256(SOURCE.read_bytes() + HEADER.read_bytes())
    h.update(repr((FLAGS, platform.machine(), sys.platform, _native._compiler(),
                   _native._cpu_key())).encode())
    return settings.cache_folder() / "native" / f"sh_eval_{h.hexdigest()[:16]}.so"


def build() -> Path:
    """Compile the kernel into the cache (if not there yet).

    Raises:
        RuntimeError: no C compiler, or the compile failed (its output quoted).
    """
    out = library_path()
    if out.exists():
        return out
    cc = _native._compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set $CC, or install gcc)")
    with atomic_path(out, suffix=".so") as tmp:
        for extra in (["-march=native", "-fopenmp"], ["-fopenmp"], ["-march=native"], []):
            cmd = cc.split() + list(FLAGS) + extra + ["-o", str(tmp), str(SOURCE), "-lm"]
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
            if proc.returncode == 0:
                break
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed (exit {proc.returncode}): "
                               f"{(proc.stderr or proc.stdout).strip()[-1500:]}")
    return out


def _load() -> ctypes.CDLL | None:
    global _LIB, _FAILED
    if _LIB is not None or _FAILED is not None:
        return _LIB
    with _LOCK:
        if _LIB is None and _FAILED is None:
            try:
                lib = ctypes.CDLL(str(build()))
                lib.torchrefract_sh_eval.argtypes = [ctypes.POINTER(_ShEvalJob), ctypes.c_int]
                lib.torchrefract_sh_eval.restype = ctypes.c_int
                lib.torchrefract_sh_eval_job_size.restype = ctypes.c_int64
                lib.torchrefract_sh_eval_half.restype = ctypes.c_int
                if lib.torchrefract_sh_eval_job_size() != ctypes.sizeof(_ShEvalJob):
                    raise RuntimeError("the library's job layout differs from native.py's")
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


__all__ = ["CPAD", "available", "build", "evaluate", "evaluate_points", "library_path",
           "padded_coeffs", "table_half"]
