"""Measure candidate tools for fused per-pixel shading kernels, side by side.

One representative per-pixel kernel (refract, march a depth image, bisect, refract again,
look up a lat-long environment twice, Fresnel-blend) written once per tool, run in one
process on the same inputs, its result checked against eager torch:

  eager     torch, vectorised over rays, a fixed 32-step march with masks
  compile   torch.compile (inductor) of that same function (dynamic=True, as the project)
  numba     @njit(parallel=True, cache=True), prange over rays, early exit
  c         plain C + OpenMP, gcc -O2 -fopenmp into a .so called through ctypes, early exit
  cnative   the same C built with -march=native as well
  warp      a warp-lang kernel on the CPU device, torch tensors passed zero-copy
  cppext    (only when asked for) the same C source as a torch C++ extension (load_inline)

Per tool: the cold first call (compile included) in this process; the first call of a
second process that finds the caches this one wrote; the median of 7 runs at 1 and at 2
threads (interleaved); the largest absolute difference from eager and how many rays differ
by > 1e-3; and how many cores *other* processes used meanwhile (the figures are only
comparable when that is near 0: on a shared machine, rerun when it is not). The caches go
into a fresh temporary folder per run (so "cold" is cold), removed at the end unless
--cache-dir is given. docs/kernel_tools.md has the results and what they mean.

Not part of the package, and not run by the tests: it needs numba and warp-lang, which
the project does not install. A tool whose package is missing is skipped. Run it from a
virtual environment of its own, e.g.

    python3 -m venv /tmp/kt && /tmp/kt/bin/pip install torch==2.13.0 numpy numba warp-lang
    /tmp/kt/bin/python scripts/kernel_tools.py          # about 1.5-2 minutes on 2 cores
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays", type=int, default=200_000)
    ap.add_argument("--runs", type=int, default=7, help="timed runs per thread count")
    ap.add_argument("--tools", default="eager,compile,numba,c,cnative,warp",
                    help="comma-separated subset of eager,compile,numba,c,cnative,warp,cppext "
                         "(cnative: the C kernel built with -march=native too; cppext, not "
                         "run by default: the same source as a torch C++ extension)")
    ap.add_argument("--cache-dir", help="keep the caches here (default: a temporary folder)")
    ap.add_argument("--json", help="also write the measurements to this file")
    ap.add_argument("--quiet-wait", type=float, default=10.0,
                    help="before each tool's timing, wait up to this many seconds for the "
                         "other processes on the machine to go quiet (shared machines)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


ARGS = _args()
CACHE = Path(ARGS.cache_dir or tempfile.mkdtemp(prefix="kernel_tools_")).resolve()
# Every tool's on-disk cache goes under CACHE; these must be set before the imports.
os.environ["NUMBA_CACHE_DIR"] = str(CACHE / "numba")
os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(CACHE / "inductor")
os.environ.setdefault("TORCHINDUCTOR_CPP_DYNAMIC_THREADS", "1")  # see docs: thread count

_IMPORT_S: dict[str, float] = {}
_t = time.perf_counter()
import numpy as np  # noqa: E402
import torch  # noqa: E402
_IMPORT_S["torch"] = time.perf_counter() - _t

try:
    _t = time.perf_counter()
    import numba as nb
    _IMPORT_S["numba"] = time.perf_counter() - _t
except ImportError:
    nb = None
try:
    _t = time.perf_counter()
    import warp as wp
    wp.config.kernel_cache_dir = str(CACHE / "warp")
    wp.config.log_level = wp.LOG_WARNING
    _IMPORT_S["warp"] = time.perf_counter() - _t
except ImportError:
    wp = None

# ---------------------------------------------------------------------------------------
# The problem: sizes, constants (all exactly representable in float32) and inputs.
STEPS, BISECT = 32, 8
H = W = 256                     # depth image
HE, WE = 256, 512               # environment map (lat-long)
_c32 = lambda x: float(np.float32(x))  # noqa: E731
ETA_IN, ETA_OUT = _c32(1 / 1.5), _c32(1.5)
ETA_IN2, ETA_OUT2 = _c32(np.float32(ETA_IN) * np.float32(ETA_IN)), _c32(2.25)
FOCAL = _c32(0.5 * W / math.tan(math.radians(40) / 2))
CX, CY = W / 2, H / 2
DS, SMAX = 0.0625, 2.0          # march step and length (SMAX = STEPS * DS)
INV_2PI, INV_PI = _c32(0.5 / math.pi), _c32(1 / math.pi)
CONSTS = np.array([ETA_IN, ETA_IN2, ETA_OUT, ETA_OUT2, FOCAL, CX, CY, DS, SMAX, INV_2PI,
                   INV_PI], dtype=np.float32)


def make_inputs(n: int, seed: int = 0):
    """Rays that enter glass at depth 2..2.6 and march towards a back layer at 2.7..4.0
    (some never reach it); back normals tilted enough that some exits are TIR."""
    g = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    px, py = W * (0.1 + 0.8 * rnd(n)), H * (0.1 + 0.8 * rnd(n))
    d = torch.stack([(px - CX) / FOCAL, (py - CY) / FOCAL, torch.ones(n)], 1)
    d = d / d.norm(dim=1, keepdim=True)
    p = d * ((2.0 + 0.6 * rnd(n)) / d[:, 2])[:, None]
    nrm = torch.randn(n, 3, generator=g) * 0.35 + torch.tensor([0.0, 0.0, -1.0])
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float32),
                            torch.arange(W, dtype=torch.float32), indexing="ij")
    depth = 3.2 + 0.5 * torch.sin(xx / 23) * torch.cos(yy / 31) + 0.3 * (xx / W - 0.5)
    nback = torch.stack([0.45 * torch.sin(xx / 17), 0.45 * torch.cos(yy / 19),
                         torch.ones_like(xx)], -1)
    nback = nback / nback.norm(dim=-1, keepdim=True)
    ey, ex = torch.meshgrid(torch.arange(HE, dtype=torch.float32),
                            torch.arange(WE, dtype=torch.float32), indexing="ij")
    env = torch.stack([1.0 + torch.sin(ex / 9 + k) * torch.cos(ey / (7 + 3 * k)) + 0.2 * k
                       for k in range(3)], -1).clamp_min(0.0)
    return [x.contiguous().float() for x in (p, d, nrm, depth, nback, env)]


# ---------------------------------------------------------------------------------------
# (1) torch eager, vectorised over rays; (2) torch.compile of the same function.
def shade_torch(p, d, n, depth, nback, env):
    def dot(a, b):
        return a[:, 0:1] * b[:, 0:1] + a[:, 1:2] * b[:, 1:2] + a[:, 2:3] * b[:, 2:3]

    def refract(d, n, eta, eta2):  # -> Fresnel F, refracted (TIR: reflected), reflected
        cosi = -dot(d, n)
        n = torch.where(cosi < 0, -n, n)
        cosi = cosi.abs()
        k = 1 - eta2 * (1 - cosi * cosi)
        cost = torch.sqrt(k.clamp_min(0))
        r = d + (2 * cosi) * n
        a = eta * cosi - cost
        rs = a / (eta * cosi + cost)
        rp = (eta * cost - cosi) / (eta * cost + cosi)
        tir = k < 0
        return (torch.where(tir, 1.0, 0.5 * (rs * rs + rp * rp)),
                torch.where(tir, r, eta * d + a * n), r)

    def pixel(q):  # pinhole projection -> nearest pixel (clamped), and the point's depth
        z = q[:, 2:3]
        ix = (FOCAL * q[:, 0:1] / z + CX).floor().clamp(0, W - 1).long()
        iy = (FOCAL * q[:, 1:2] / z + CY).floor().clamp(0, H - 1).long()
        return iy, ix, z

    def envmap(w):  # bilinear lat-long lookup, wrapping in u, clamped in v
        u = torch.atan2(w[:, 0:1], -w[:, 2:3]) * INV_2PI + 0.5
        v = torch.acos(w[:, 1:2].clamp(-1, 1)) * INV_PI
        x, y = u * WE - 0.5, v * HE - 0.5
        x0, y0 = x.floor(), y.floor()
        fx, fy = x - x0, y - y0
        xi, yi = x0.long(), y0.long()
        xa = (xi % WE + WE) % WE
        xb = (xa + 1) % WE
        ya, yb = yi.clamp(0, HE - 1)[:, 0], (yi + 1).clamp(0, HE - 1)[:, 0]
        xa, xb = xa[:, 0], xb[:, 0]
        top = env[ya, xa] * (1 - fx) + env[ya, xb] * fx
        bot = env[yb, xa] * (1 - fx) + env[yb, xb] * fx
        return top * (1 - fy) + bot * fy

    F, t, r = refract(d, n, ETA_IN, ETA_IN2)
    found = torch.zeros_like(F, dtype=torch.bool)
    lo = torch.full_like(F, SMAX)
    hi = lo
    for k in range(1, STEPS + 1):  # fixed-length march: first crossing wins
        s = k * DS
        iy, ix, z = pixel(p + s * t)
        hit = (z >= depth[iy, ix]) & ~found
        hi = torch.where(hit, s, hi)
        lo = torch.where(hit, s - DS, lo)
        found = found | hit
    for _ in range(BISECT):  # misses keep lo = hi = SMAX
        mid = 0.5 * (lo + hi)
        iy, ix, z = pixel(p + mid * t)
        hit = z >= depth[iy, ix]
        hi = torch.where(hit, mid, hi)
        lo = torch.where(hit, lo, mid)
    iy, ix, _ = pixel(p + hi * t)
    _, e, _ = refract(t, nback[iy[:, 0], ix[:, 0]], ETA_OUT, ETA_OUT2)
    return F * envmap(r) + (1 - F) * envmap(e)


# ---------------------------------------------------------------------------------------
# (3) numba: one ray per prange iteration, float32 throughout (np.float32 constants: a
# bare Python float would promote the arithmetic to float64).
if nb is not None:
    _f = np.float32

    @nb.njit(cache=True, inline="always")
    def _nb_refract(dx, dy, dz, nx, ny, nz, eta, eta2):
        cosi = -(dx * nx + dy * ny + dz * nz)
        if cosi < 0:
            nx, ny, nz, cosi = -nx, -ny, -nz, -cosi
        k = _f(1) - eta2 * (_f(1) - cosi * cosi)
        c2 = _f(2) * cosi
        rx, ry, rz = dx + c2 * nx, dy + c2 * ny, dz + c2 * nz
        if k < 0:
            return _f(1), rx, ry, rz, rx, ry, rz
        cost = math.sqrt(k)
        a = eta * cosi - cost
        rs = a / (eta * cosi + cost)
        rp = (eta * cost - cosi) / (eta * cost + cosi)
        return (_f(0.5) * (rs * rs + rp * rp), eta * dx + a * nx, eta * dy + a * ny,
                eta * dz + a * nz, rx, ry, rz)

    @nb.njit(cache=True, inline="always")
    def _nb_pix(a, z, f, c, size):
        v = np.floor(f * a / z + c)
        return int(min(max(v, _f(0)), _f(size - 1)))

    @nb.njit(cache=True, inline="always")
    def _nb_env(env, wx, wy, wz, i2pi, ipi, out, i, w):
        he, we = env.shape[0], env.shape[1]
        u = math.atan2(wx, -wz) * i2pi + _f(0.5)
        v = math.acos(min(max(wy, _f(-1)), _f(1))) * ipi
        x, y = u * _f(we) - _f(0.5), v * _f(he) - _f(0.5)
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = x - x0, y - y0
        xi, yi = int(x0), int(y0)
        xa = (xi % we + we) % we
        xb = (xa + 1) % we
        ya, yb = min(max(yi, 0), he - 1), min(max(yi + 1, 0), he - 1)
        for c in range(3):
            top = env[ya, xa, c] * (_f(1) - fx) + env[ya, xb, c] * fx
            bot = env[yb, xa, c] * (_f(1) - fx) + env[yb, xb, c] * fx
            out[i, c] += w * (top * (_f(1) - fy) + bot * fy)

    @nb.njit(parallel=True, cache=True)
    def shade_numba(p, d, n, depth, nback, env, c, out):
        h, w = depth.shape
        for i in nb.prange(p.shape[0]):
            px, py, pz = p[i, 0], p[i, 1], p[i, 2]
            F, tx, ty, tz, rx, ry, rz = _nb_refract(d[i, 0], d[i, 1], d[i, 2], n[i, 0],
                                                    n[i, 1], n[i, 2], c[0], c[1])
            lo = hi = c[8]
            for k in range(1, STEPS + 1):
                s = _f(k) * c[7]
                qx, qy, qz = px + s * tx, py + s * ty, pz + s * tz
                if qz >= depth[_nb_pix(qy, qz, c[4], c[6], h), _nb_pix(qx, qz, c[4], c[5], w)]:
                    lo, hi = s - c[7], s
                    break
            for _ in range(BISECT):
                mid = _f(0.5) * (lo + hi)
                qx, qy, qz = px + mid * tx, py + mid * ty, pz + mid * tz
                if qz >= depth[_nb_pix(qy, qz, c[4], c[6], h), _nb_pix(qx, qz, c[4], c[5], w)]:
                    hi = mid
                else:
                    lo = mid
            qx, qy, qz = px + hi * tx, py + hi * ty, pz + hi * tz
            iy, ix = _nb_pix(qy, qz, c[4], c[6], h), _nb_pix(qx, qz, c[4], c[5], w)
            _, ex, ey, ez, _, _, _ = _nb_refract(tx, ty, tz, nback[iy, ix, 0],
                                                 nback[iy, ix, 1], nback[iy, ix, 2], c[2], c[3])
            out[i, 0] = out[i, 1] = out[i, 2] = _f(0)
            _nb_env(env, rx, ry, rz, c[9], c[10], out, i, F)
            _nb_env(env, ex, ey, ez, c[9], c[10], out, i, _f(1) - F)

# ---------------------------------------------------------------------------------------
# (4) plain C + OpenMP through ctypes. Same float32 arithmetic: no fast-math, no FMA
# contraction (the project's csrc/ uses the same rule).
C_SOURCE = r"""
#include <math.h>
#include <stdint.h>
typedef struct { float x, y, z; } v3;
static inline v3 V(float x, float y, float z) { v3 r = {x, y, z}; return r; }
static inline v3 ray(v3 p, float s, v3 t) { return V(p.x + s * t.x, p.y + s * t.y, p.z + s * t.z); }

static float refract3(v3 d, v3 n, float eta, float eta2, v3 *t, v3 *r) {
  float cosi = -(d.x * n.x + d.y * n.y + d.z * n.z);
  if (cosi < 0.f) { n = V(-n.x, -n.y, -n.z); cosi = -cosi; }
  float k = 1.f - eta2 * (1.f - cosi * cosi), c2 = 2.f * cosi;
  *r = V(d.x + c2 * n.x, d.y + c2 * n.y, d.z + c2 * n.z);
  if (k < 0.f) { *t = *r; return 1.f; }                       /* TIR -> reflect */
  float cost = sqrtf(k), a = eta * cosi - cost;
  float rs = a / (eta * cosi + cost), rp = (eta * cost - cosi) / (eta * cost + cosi);
  *t = V(eta * d.x + a * n.x, eta * d.y + a * n.y, eta * d.z + a * n.z);
  return 0.5f * (rs * rs + rp * rp);
}

static inline int pix(float a, float z, float f, float c, int size) {
  float v = floorf(f * a / z + c);
  return (int)fminf(fmaxf(v, 0.f), (float)(size - 1));
}

static void envmap(const float *env, int he, int we, v3 w, const float *c, float wt, float *o) {
  float u = atan2f(w.x, -w.z) * c[9] + 0.5f;
  float v = acosf(fminf(fmaxf(w.y, -1.f), 1.f)) * c[10];
  float x = u * (float)we - 0.5f, y = v * (float)he - 0.5f;
  float x0 = floorf(x), y0 = floorf(y), fx = x - x0, fy = y - y0;
  int xi = (int)x0, yi = (int)y0;
  int xa = (xi % we + we) % we, xb = (xa + 1) % we;
  int ya = yi < 0 ? 0 : (yi > he - 1 ? he - 1 : yi);
  int yb = yi + 1 < 0 ? 0 : (yi + 1 > he - 1 ? he - 1 : yi + 1);
  const float *e00 = env + ((int64_t)ya * we + xa) * 3, *e01 = env + ((int64_t)ya * we + xb) * 3;
  const float *e10 = env + ((int64_t)yb * we + xa) * 3, *e11 = env + ((int64_t)yb * we + xb) * 3;
  for (int k = 0; k < 3; k++) {
    float top = e00[k] * (1.f - fx) + e01[k] * fx, bot = e10[k] * (1.f - fx) + e11[k] * fx;
    o[k] += wt * (top * (1.f - fy) + bot * fy);
  }
}

void shade(int64_t n, const float *p, const float *d, const float *nrm, const float *depth,
           int h, int w, const float *nback, const float *env, int he, int we,
           const float *c, int steps, int bisect, float *out, int threads) {
  #pragma omp parallel for num_threads(threads) schedule(static)
  for (int64_t i = 0; i < n; i++) {
    v3 P = V(p[3 * i], p[3 * i + 1], p[3 * i + 2]), t, r, e, r2;
    float F = refract3(V(d[3 * i], d[3 * i + 1], d[3 * i + 2]),
                       V(nrm[3 * i], nrm[3 * i + 1], nrm[3 * i + 2]), c[0], c[1], &t, &r);
    float lo = c[8], hi = c[8];
    for (int k = 1; k <= steps; k++) {                          /* early exit */
      float s = (float)k * c[7];
      v3 q = ray(P, s, t);
      if (q.z >= depth[(int64_t)pix(q.y, q.z, c[4], c[6], h) * w + pix(q.x, q.z, c[4], c[5], w)]) {
        lo = s - c[7]; hi = s; break;
      }
    }
    for (int b = 0; b < bisect; b++) {
      float mid = 0.5f * (lo + hi);
      v3 q = ray(P, mid, t);
      if (q.z >= depth[(int64_t)pix(q.y, q.z, c[4], c[6], h) * w + pix(q.x, q.z, c[4], c[5], w)])
        hi = mid;
      else
        lo = mid;
    }
    v3 x = ray(P, hi, t);
    int64_t px = (int64_t)pix(x.y, x.z, c[4], c[6], h) * w + pix(x.x, x.z, c[4], c[5], w);
    const float *nb = nback + 3 * px;
    refract3(t, V(nb[0], nb[1], nb[2]), c[2], c[3], &e, &r2);
    float *o = out + 3 * i;
    o[0] = o[1] = o[2] = 0.f;
    envmap(env, he, we, r, c, F, o);
    envmap(env, he, we, e, c, 1.f - F, o);
  }
}
"""
C_FLAGS = ["-O2", "-fopenmp", "-shared", "-fPIC", "-ffp-contract=off", "-fno-fast-math"]


def c_library(extra: tuple[str, ...] = ()) -> tuple[ctypes.CDLL, float]:
    """Build (unless cached) and load the C kernel; returns it and the build's seconds."""
    cc = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
    if not cc:
        raise RuntimeError("no C compiler")
    flags = C_FLAGS + list(extra)
    key = hashlib.sha256((C_SOURCE + repr(flags) + cc).encode()).hexdigest()[:16]
    so = CACHE / "c" / f"shade_{key}.so"
    build_s = 0.0
    if not so.exists():
        so.parent.mkdir(parents=True, exist_ok=True)
        src = so.with_suffix(".c")
        src.write_text(C_SOURCE)
        t0 = time.perf_counter()
        subprocess.run([cc, *flags, str(src), "-o", str(so) + ".tmp", "-lm"], check=True)
        os.replace(str(so) + ".tmp", so)
        build_s = time.perf_counter() - t0
    lib = ctypes.CDLL(str(so))
    P, I, L = ctypes.c_void_p, ctypes.c_int, ctypes.c_int64
    lib.shade.argtypes = [L, P, P, P, P, I, I, P, P, I, I, P, I, I, P, I]
    lib.shade.restype = None
    return lib, build_s


def cpp_extension():
    """The same C source as a torch C++ extension (torch.utils.cpp_extension.load_inline:
    g++, ninja and torch's headers), taking tensors; built into CACHE/cppext."""
    from torch.utils.cpp_extension import load_inline
    wrapper = """
#include <torch/extension.h>
void shade_t(torch::Tensor p, torch::Tensor d, torch::Tensor n, torch::Tensor depth,
             torch::Tensor nback, torch::Tensor env, torch::Tensor c, int64_t steps,
             int64_t bisect, torch::Tensor out, int64_t threads) {
  shade(p.size(0), p.data_ptr<float>(), d.data_ptr<float>(), n.data_ptr<float>(),
        depth.data_ptr<float>(), depth.size(0), depth.size(1), nback.data_ptr<float>(),
        env.data_ptr<float>(), env.size(0), env.size(1), c.data_ptr<float>(), steps, bisect,
        out.data_ptr<float>(), threads);
}
"""
    build = CACHE / "cppext"
    build.mkdir(parents=True, exist_ok=True)
    return load_inline("kernel_tools_shade", [C_SOURCE + wrapper], functions=["shade_t"],
                       extra_cflags=["-O2", "-fopenmp", "-ffp-contract=off"],
                       extra_ldflags=["-fopenmp"], build_directory=str(build))


def shade_c(lib, threads, p, d, n, depth, nback, env, consts, out):
    ptr = lambda t: t.data_ptr()  # noqa: E731
    lib.shade(p.shape[0], ptr(p), ptr(d), ptr(n), ptr(depth), H, W, ptr(nback), ptr(env),
              HE, WE, ptr(consts), STEPS, BISECT, ptr(out), threads)


# ---------------------------------------------------------------------------------------
# (5) NVIDIA Warp: the same kernel in Warp's Python dialect (compiled to C++ and built by
# Warp's bundled clang/LLVM on the CPU; NVRTC on CUDA). Float literals are float32.
if wp is not None:
    @wp.func
    def _wp_refract(d: wp.vec3, n: wp.vec3, eta: float, eta2: float):
        cosi = -(d[0] * n[0] + d[1] * n[1] + d[2] * n[2])
        m = n
        if cosi < 0.0:
            m = -n
            cosi = -cosi
        k = 1.0 - eta2 * (1.0 - cosi * cosi)
        r = d + (2.0 * cosi) * m
        F = float(1.0)
        t = r
        if k >= 0.0:
            cost = wp.sqrt(k)
            a = eta * cosi - cost
            rs = a / (eta * cosi + cost)
            rp = (eta * cost - cosi) / (eta * cost + cosi)
            F = 0.5 * (rs * rs + rp * rp)
            t = eta * d + a * m
        return F, t, r

    @wp.func
    def _wp_pix(a: float, z: float, f: float, c: float, size: int):
        return int(wp.min(wp.max(wp.floor(f * a / z + c), 0.0), float(size - 1)))

    @wp.func
    def _wp_env(env: wp.array2d(dtype=wp.vec3), w: wp.vec3, i2pi: float, ipi: float):
        he, we = env.shape[0], env.shape[1]
        u = wp.atan2(w[0], -w[2]) * i2pi + 0.5
        v = wp.acos(wp.min(wp.max(w[1], -1.0), 1.0)) * ipi
        x = u * float(we) - 0.5
        y = v * float(he) - 0.5
        x0 = wp.floor(x)
        y0 = wp.floor(y)
        fx = x - x0
        fy = y - y0
        xi = int(x0)
        yi = int(y0)
        xa = (xi % we + we) % we
        xb = (xa + 1) % we
        ya = wp.min(wp.max(yi, 0), he - 1)
        yb = wp.min(wp.max(yi + 1, 0), he - 1)
        top = env[ya, xa] * (1.0 - fx) + env[ya, xb] * fx
        bot = env[yb, xa] * (1.0 - fx) + env[yb, xb] * fx
        return top * (1.0 - fy) + bot * fy

    @wp.kernel
    def shade_warp(p: wp.array(dtype=wp.vec3), d: wp.array(dtype=wp.vec3),
                   n: wp.array(dtype=wp.vec3), depth: wp.array2d(dtype=float),
                   nback: wp.array2d(dtype=wp.vec3), env: wp.array2d(dtype=wp.vec3),
                   c: wp.array(dtype=float), steps: int, bisect: int,
                   out: wp.array(dtype=wp.vec3)):
        i = wp.tid()
        h, w = depth.shape[0], depth.shape[1]
        P = p[i]
        F, t, r = _wp_refract(d[i], n[i], c[0], c[1])
        lo = float(c[8])
        hi = float(c[8])
        for k in range(1, steps + 1):
            s = float(k) * c[7]
            q = P + s * t
            iy = _wp_pix(q[1], q[2], c[4], c[6], h)
            if q[2] >= depth[iy, _wp_pix(q[0], q[2], c[4], c[5], w)]:
                lo = s - c[7]
                hi = s
                break
        for _b in range(bisect):
            mid = 0.5 * (lo + hi)
            q = P + mid * t
            iy = _wp_pix(q[1], q[2], c[4], c[6], h)
            if q[2] >= depth[iy, _wp_pix(q[0], q[2], c[4], c[5], w)]:
                hi = mid
            else:
                lo = mid
        x = P + hi * t
        nb_ = nback[_wp_pix(x[1], x[2], c[4], c[6], h), _wp_pix(x[0], x[2], c[4], c[5], w)]
        F2, e, r2 = _wp_refract(t, nb_, c[2], c[3])
        out[i] = F * _wp_env(env, r, c[9], c[10]) + (1.0 - F) * _wp_env(env, e, c[9], c[10])

    def run_warp(args, consts, out):
        p, d, n, depth, nback, env = args
        v3 = wp.vec3
        wp.launch(shade_warp, dim=p.shape[0], device="cpu",
                  inputs=[wp.from_torch(p, dtype=v3), wp.from_torch(d, dtype=v3),
                          wp.from_torch(n, dtype=v3), wp.from_torch(depth),
                          wp.from_torch(nback, dtype=v3), wp.from_torch(env, dtype=v3),
                          wp.from_torch(consts), STEPS, BISECT, wp.from_torch(out, dtype=v3)])


# ---------------------------------------------------------------------------------------
def say(msg: str) -> None:
    print(f"[kernel_tools] {msg}", file=sys.stderr, flush=True)


def runners(tools, inputs):
    """name -> (setup() -> (first-call seconds, fn(threads) -> output)), for each tool."""
    consts = torch.from_numpy(CONSTS)
    out = torch.empty(inputs[0].shape[0], 3)

    def eager():
        t0 = time.perf_counter()
        shade_torch(*inputs)
        first = time.perf_counter() - t0

        def go(k):
            torch.set_num_threads(k)
            return shade_torch(*inputs)
        return first, go

    def compiled():
        import torch._dynamo
        from torch._dynamo.utils import counters
        fn = torch.compile(shade_torch, dynamic=True)
        t0 = time.perf_counter()
        fn(*inputs)
        first = time.perf_counter() - t0
        graphs_first = counters["stats"].get("unique_graphs", 0)
        runners.compile_stats = lambda: {  # noqa: E731  (read after the timed runs)
            "graph_breaks": sum(counters["graph_break"].values()),
            "graphs_first_call": graphs_first,
            "graphs_after_runs": counters["stats"].get("unique_graphs", 0)}

        def go(k):
            torch.set_num_threads(k)
            return fn(*inputs)
        return first, go

    def numba_():
        arrs = [x.numpy() for x in inputs]
        o = out.numpy()
        t0 = time.perf_counter()
        shade_numba(*arrs, CONSTS, o)
        first = time.perf_counter() - t0
        runners.numba_stats = {"cache_hits": sum(shade_numba.stats.cache_hits.values()),
                               "threading_layer": nb.threading_layer()}

        def go(k):
            nb.set_num_threads(k)
            shade_numba(*arrs, CONSTS, o)
            return out
        return first, go

    def c_(extra=()):
        t0 = time.perf_counter()
        lib, build = c_library(extra)
        shade_c(lib, 1, *inputs, consts, out)
        first = time.perf_counter() - t0
        runners.c_build_s = getattr(runners, "c_build_s", {})
        runners.c_build_s[" ".join(C_FLAGS + list(extra))] = build

        def go(k):
            shade_c(lib, k, *inputs, consts, out)
            return out
        return first, go

    def cppext():
        t0 = time.perf_counter()
        mod = cpp_extension()
        mod.shade_t(*inputs, consts, STEPS, BISECT, out, 1)
        first = time.perf_counter() - t0

        def go(k):
            mod.shade_t(*inputs, consts, STEPS, BISECT, out, k)
            return out
        return first, go

    def warp_():
        t0 = time.perf_counter()
        wp.init()
        run_warp(inputs, consts, out)
        first = time.perf_counter() - t0

        def go(k):  # Warp has no thread count for CPU launches: one thread either way
            run_warp(inputs, consts, out)
            return out
        return first, go

    table = {"eager": ("torch eager", eager), "compile": ("torch.compile", compiled),
             "numba": ("numba prange", numba_), "c": ("C+OpenMP -O2 (ctypes)", c_),
             "cnative": ("C+OpenMP -O2 -march=native", lambda: c_(("-march=native",))),
             "warp": ("warp (cpu)", warp_), "cppext": ("C++ torch extension", cppext)}
    avail = {"numba": nb is not None, "warp": wp is not None}
    return {k: table[k] for k in tools if avail.get(k, True)}


def child() -> None:
    """Second process: the first call of each tool with the caches the parent wrote."""
    inputs = make_inputs(ARGS.rays)
    res = {}
    for key, (_, setup) in runners(ARGS.tools.split(","), inputs).items():
        if key == "eager":
            continue
        try:
            first, _ = setup()
            res[key] = first + _IMPORT_S.get({"numba": "numba", "warp": "warp"}.get(key, ""), 0)
        except Exception as exc:  # noqa: BLE001
            res[key] = f"failed: {type(exc).__name__}: {exc}"
    res["numba_stats"] = getattr(runners, "numba_stats", None)
    print("CHILD " + json.dumps(res))


class OthersLoad:
    """CPU cores used by *other* processes meanwhile: all CPUs' busy time from /proc/stat
    minus this process's own CPU time, over the wall time (Linux only; else None)."""

    TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100

    @staticmethod
    def sample():
        try:
            v = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]
        except OSError:
            return None
        t = os.times()
        return time.perf_counter(), (sum(v) - v[3] - v[4]) / OthersLoad.TICK, t.user + t.system

    def __init__(self):
        self.start = self.sample()

    def cores(self):
        end = self.sample()
        if self.start is None or end is None:
            return None
        wall = end[0] - self.start[0]
        return max(0.0, (end[1] - self.start[1]) - (end[2] - self.start[2])) / wall


def wait_quiet(limit: float, threshold: float = 0.15) -> float:
    """Wait (up to ``limit`` s) until other processes use under ``threshold`` cores over
    half a second; returns the seconds waited."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < limit:
        probe = OthersLoad()
        time.sleep(0.5)
        load = probe.cores()
        if load is None or load < threshold:
            break
    return time.perf_counter() - t0


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return "?"


def main() -> None:
    tools = ARGS.tools.split(",")
    say(f"cache folder {CACHE}; {os.cpu_count()} CPUs ({cpu_model()}); torch "
        f"{torch.__version__}, numba {nb.__version__ if nb else '-'}, "
        f"warp {wp.config.version if wp else '-'}")
    inputs = make_inputs(ARGS.rays)
    rows, ref, outputs = [], None, {}
    for key, (label, setup) in runners(tools, inputs).items():
        say(f"{label}: first call (compiles on a cold cache) ...")
        torch.set_num_threads(2)
        try:
            first, go = setup()
        except Exception as exc:  # noqa: BLE001
            say(f"{label}: FAILED {type(exc).__name__}: {exc}")
            rows.append({"key": key, "tool": label, "error": f"{type(exc).__name__}: {exc}"})
            continue
        warmup = {}
        for k in (1, 2):  # warm-up at both thread counts (torch.compile recompiles here)
            t0 = time.perf_counter()
            go(k)
            warmup[k] = time.perf_counter() - t0
        waited = wait_quiet(ARGS.quiet_wait)
        times, load = {1: [], 2: []}, {1: [], 2: []}
        for _ in range(ARGS.runs):  # interleaved, so that a change of load hits both
            for k in (1, 2):
                probe = OthersLoad()
                t0 = time.perf_counter()
                res = go(k)
                times[k].append(time.perf_counter() - t0)
                load[k].append(probe.cores() or 0.0)
        ms = {k: 1e3 * statistics.median(v) for k, v in times.items()}
        res = outputs[key] = res.clone()
        if ref is None:
            ref = res
        diff = (res - ref).abs().amax(dim=1)
        rows.append({"key": key, "tool": label, "first_s": first, "ms1": ms[1], "ms2": ms[2],
                     "max_abs_diff": diff.max().item(),
                     "rays_over_1e-3": int((diff > 1e-3).sum()),
                     "others_load": max(statistics.mean(load[1]), statistics.mean(load[2])),
                     "waited_s": waited, "warmup_s": warmup,
                     "runs_ms": {k: [1e3 * x for x in v] for k, v in times.items()}})
        say(f"{label}: first {first:.2f} s, {ms[1]:.1f} ms @1, {ms[2]:.1f} ms @2 (others "
            f"used {rows[-1]['others_load']:.2f} cores meanwhile; waited {waited:.0f} s)")
    torch.set_num_threads(2)

    say("second process: first calls with the caches written above ...")
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--child", "--cache-dir", str(CACHE),
                           "--rays", str(ARGS.rays), "--tools", ARGS.tools],
                          capture_output=True, text=True)
    line = [x for x in proc.stdout.splitlines() if x.startswith("CHILD ")]
    warm = json.loads(line[-1][6:]) if line else {}
    if not line:
        say("second process failed:\n" + proc.stderr[-2000:])
    say(f"second process took {time.perf_counter() - t0:.1f} s")

    extra = {"compile": getattr(runners, "compile_stats", lambda: None)(),
             "numba_cold": getattr(runners, "numba_stats", None),
             "numba_warm": warm.get("numba_stats"),
             "c_build_s": getattr(runners, "c_build_s", None),
             "import_s": _IMPORT_S}
    print(f"\n{ARGS.rays} rays, {STEPS}+{BISECT} march steps, depth {H}x{W}, env {WE}x{HE}; "
          f"median of {ARGS.runs}; {os.cpu_count()} CPUs: {cpu_model()}")
    first_ok = next((r["key"] for r in rows if "error" not in r), "-")
    hdr = ("tool", "first call s", "2nd process s", "ms @1 thr", "ms @2 thr", "1->2",
           f"max|diff| vs {first_ok}", "rays>1e-3", "others' load")
    print("| " + " | ".join(hdr) + " |\n|" + "---|" * len(hdr))
    for r in rows:
        if "error" in r:
            print(f"| {r['tool']} | failed: {r['error']} |")
            continue
        w = warm.get(r["key"], "-")
        w = f"{w:.2f}" if isinstance(w, float) else str(w)
        print(f"| {r['tool']} | {r['first_s']:.2f} | {w} | {r['ms1']:.1f} | {r['ms2']:.1f} | "
              f"{r['ms1'] / r['ms2']:.2f}x | {r['max_abs_diff']:.2e} | {r['rays_over_1e-3']} | "
              f"{r['others_load']:.2f} |")
    cs = extra["compile"]
    if cs:
        print(f"\ntorch.compile: {cs['graph_breaks']} graph break(s); {cs['graphs_first_call']} "
              f"graph(s) compiled by the first call, {cs['graphs_after_runs']} after the runs at "
              f"1 and 2 threads (TORCHINDUCTOR_CPP_DYNAMIC_THREADS="
              f"{os.environ['TORCHINDUCTOR_CPP_DYNAMIC_THREADS']})")
        w = next((r["warmup_s"] for r in rows if r["key"] == "compile"), None)
        if w:
            print(f"torch.compile: first call at 1 thread after compiling at 2: {w[1]:.2f} s")
    if "c" in outputs:
        print("max|diff| vs the C kernel: " + ", ".join(
            f"{k} {(v - outputs['c']).abs().max().item():.2e}" for k, v in outputs.items()
            if k != "c"))
    for flags, sec in (extra["c_build_s"] or {}).items():
        print(f"C: gcc {flags}: build {sec:.2f} s (included in its first call)")
    if extra["numba_cold"]:
        print(f"numba: threading layer {extra['numba_cold']['threading_layer']}; cache hits "
              f"cold {extra['numba_cold']['cache_hits']}, second process "
              f"{(extra['numba_warm'] or {}).get('cache_hits')}")
    print("imports (s): " + ", ".join(f"{k} {v:.2f}" for k, v in _IMPORT_S.items())
          + " (the second process's numba/warp figures include their import)")
    if ARGS.json:
        Path(ARGS.json).write_text(json.dumps({"rows": rows, "warm": warm, **extra}, indent=1))
    if not ARGS.cache_dir:
        shutil.rmtree(CACHE, ignore_errors=True)


if __name__ == "__main__":
    child() if ARGS.child else main()
