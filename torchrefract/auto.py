"""The ``auto`` policy: per scene, the cheapest method variant whose measured error on
similar scenes is within ``auto_tolerance`` of the best one ("model no more than a scene
needs"). It picks methods; it shades nothing itself.

The measurements are the speed/accuracy chart's (``scripts/pareto.py``), condensed by
``scripts/build_auto_table.py`` into ``torchrefract/tables/auto_v1.json``: per suite scene
its features and, per variant, time per frame and FLIP against Mitsuba truth. For a scene:

1. Features from the scene alone: roughness alpha (a map: the middle of its range), IOR,
   and thinness (smallest / largest principal extent of the area-weighted surface).
2. The two nearest table scenes in (log10 alpha / 0.5, thinness / 0.2, IOR / 0.5),
   weighted by inverse distance, predict each variant's FLIP and time.
3. The fastest variant predicted within ``auto_tolerance`` of the best predicted FLIP.
4. Below ``SMOOTH_ALPHA`` only ``specular``'s variants (a smooth surface needs no cone).
5. ``tir: clamp`` is never a candidate (it fails the furnace and continuity suites).
6. Blend (``auto_blend``, default): 1.-4. evaluated on a box kernel of ``BLEND_POINTS``
   points around the scene (alpha on u = asinh(alpha / BLEND_A0) +- BLEND_HALF_WIDTH[0],
   IOR +- BLEND_HALF_WIDTH[1]); each variant weighs its share of the points less
   ``BLEND_MIN`` (renormalized) and the image is the weighted sum, so a roughness or IOR
   sweep changes the image continuously instead of jumping where the pick changes.

Without a table a rule stands in for 1.-4. (alpha < SMOOTH_ALPHA: ``specular``, else
``rousiers``). A single pick is recorded as the result's scene, a blend keeps ``auto``; every
share goes to ``RenderResult.blends``, the sidecar JSON and a sweep's manifest. Why each
threshold is where it is, and what it was measured to cost: docs/decisions.md.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchrefract.checks import ConfigError
from torchrefract.options import option, parse_options
from torchrefract.scene.model import Scene

DEFAULT_TABLE = Path(__file__).resolve().parent / "tables" / "auto_v1.json"
SCALES = {"log_alpha": 0.5, "thin": 0.2, "ior": 0.5}
SMOOTH_ALPHA = 0.04
"""Roughness below which a surface is smooth: ``specular`` only (module docstring, 4.)."""
ALPHA_FLOOR = 0.005
"""log10 alpha is taken of max(alpha, ALPHA_FLOOR) (the smooth sphere's row: -2.3)."""
EXCLUDED_TIR = ("clamp",)
"""Exit rules ``auto`` never picks (module docstring, 5.)."""
BLEND_A0 = 0.1
BLEND_HALF_WIDTH = (0.5, 0.1)
"""The blend's box kernel (module docstring, 6.): half-widths in u = asinh(alpha / BLEND_A0)
and in IOR."""
BLEND_MIN = 0.15
"""Kernel shares below this are not rendered (the others: share - BLEND_MIN, renormalized)."""
BLEND_POINTS = (32, 16)
"""Points of the kernel along u and IOR (shares are multiples of 1 / 512)."""


@dataclass(frozen=True)
class AutoOptions:
    """Settings of ``auto`` (``method_options`` in a scene)."""

    auto_tolerance: float = option(0.05, minimum=0.0, maximum=1.0)
    """FLIP (object pixels, against full truth) allowed above the most accurate variant."""
    auto_table: str | None = option(None, path=True)
    """Path of a table built by ``scripts/build_auto_table.py`` (default: the shipped one;
    relative to the scene file)."""
    auto_blend: bool = option(True, boolean=True)
    """Blend the picks around the scene's roughness and IOR (continuous in both; docstring,
    6.); ``false``: one variant per scene, switching at thresholds."""


@dataclass(frozen=True)
class Choice:
    """What ``auto`` picked for a scene and why."""

    method: str
    options: dict
    predicted_flip: float | None
    predicted_ms: float | None
    neighbours: tuple[str, ...]
    blend: tuple[tuple[str, dict, float], ...] = ()
    """(method, options, weight) of every variant rendered, weights adding up to 1, the
    largest first (``method`` and ``options`` are its); one entry away from thresholds."""


def features(scene: Scene) -> dict[str, float]:
    """Roughness, IOR and thinness of a scene (see the module docstring)."""
    from torchrefract.geometry.mesh import load_mesh  # noqa: PLC0415

    m = scene.material
    alpha = m.roughness if m.roughness_map is None else 0.5 * sum(m.roughness_range)
    mesh = load_mesh(scene.mesh, scene.transform)
    # Principal axes of the surface, not of the vertex cloud (triangle centroids weighted by
    # area: a UV sphere's vertices crowd at its poles, which tilts the vertex statistics to
    # 0.69), and the mesh's full extent along each axis.
    v = mesh.vertices.double().numpy()
    tri = v[mesh.faces.numpy()]  # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    c = tri.mean(1)
    w = area / max(area.sum(), 1e-30)
    d = c - (w[:, None] * c).sum(0)
    _, axes = np.linalg.eigh((w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0))
    ext = np.ptp(v @ axes, axis=0)  # (3,) extents along the axes
    thin = float(ext.min() / max(ext.max(), 1e-30))
    return {"log_alpha": math.log10(max(alpha, ALPHA_FLOOR)), "thin": thin, "ior": float(m.ior),
            "alpha": float(alpha)}


@functools.lru_cache(maxsize=8)
def load_table(path: str) -> dict:
    p = Path(path)
    if not p.exists():
        return {"scenes": []}
    try:
        table = json.loads(p.read_text())
    except ValueError as e:
        table = e
    if not isinstance(table, dict) or not isinstance(table.get("scenes"), list):
        raise ConfigError(f"{path}: not an auto table (a JSON object with a 'scenes' list; "
                          f"build it with scripts/build_auto_table.py)")
    return table


@dataclass(frozen=True)
class _Arrays:
    """A table as arrays: S scenes x V variants (NaN where a scene lacks a variant)."""

    keys: tuple[tuple[str, str], ...]  # (method, options as sorted JSON), V of them
    x: np.ndarray  # (S, 3) scaled features
    flip: np.ndarray  # (S, V)
    ms: np.ndarray  # (S, V)
    specular: np.ndarray  # (V,) bool
    names: tuple[str, ...]


_ARRAYS: dict[int, tuple[dict, _Arrays]] = {}


def _arrays(table: dict) -> _Arrays:
    """The table (as :func:`load_table` returns it) as arrays, built once per table."""
    hit = _ARRAYS.get(id(table))
    if hit is not None and hit[0] is table:
        return hit[1]
    if len(_ARRAYS) >= 8:
        _ARRAYS.clear()
    rows = table["scenes"]
    keys = sorted({_key(v) for r in rows for v in r["variants"]
                   if v.get("options", {}).get("tir") not in EXCLUDED_TIR})
    col = {k: j for j, k in enumerate(keys)}
    flip = np.full((len(rows), len(keys)), np.nan)
    ms = np.full((len(rows), len(keys)), np.nan)
    for i, r in enumerate(rows):
        for v in r["variants"]:
            j = col.get(_key(v))
            if j is not None:
                flip[i, j], ms[i, j] = v["flip"], v["ms"]
    x = np.array([[r["features"][k] / s for k, s in SCALES.items()] for r in rows])
    out = _Arrays(tuple(keys), x.reshape(len(rows), len(SCALES)), flip, ms,
                  np.array([k[0] == "specular" for k in keys], bool),
                  tuple(r["name"] for r in rows))
    _ARRAYS[id(table)] = (table, out)
    return out


def _key(v: dict) -> tuple[str, str]:
    return v["method"], json.dumps(v.get("options", {}), sort_keys=True)


def _crisp(t: _Arrays, f: np.ndarray, tolerance: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rule of the module docstring (1.-4.) at P feature points ``f`` (P, 3: log10 alpha,
    thinness, IOR): per point the picked variant's column (-1: no variant measured on both
    neighbours), every variant's predicted FLIP and time (P, V), and the (P, 2) neighbour
    rows."""
    x = f / np.array(list(SCALES.values()))
    dist = np.sqrt(((x[:, None, :] - t.x[None]) ** 2).sum(-1))  # (P, S)
    near = np.argsort(dist, axis=1, kind="stable")[:, :2]  # (P, k)
    w = 1.0 / (np.take_along_axis(dist, near, 1) + 1e-3)
    w = w / w.sum(1, keepdims=True)
    pf = (w[..., None] * t.flip[near]).sum(1)  # (P, V); NaN where a neighbour lacks it
    pm = (w[..., None] * t.ms[near]).sum(1)
    ok = np.isfinite(pf) & np.isfinite(pm)
    smooth = 10 ** f[:, 0] < SMOOTH_ALPHA
    spec = ok & t.specular[None]
    ok = np.where((smooth & spec.any(1))[:, None], spec, ok)  # no cone when smooth (4.)
    best = np.where(ok, pf, np.inf).min(1, keepdims=True)
    ok &= pf <= best + tolerance
    fastest = np.where(ok, pm, np.inf).min(1, keepdims=True)
    pick = np.where(ok & (pm == fastest), pf, np.inf).argmin(1)  # ties: the more accurate
    return np.where(ok.any(1), pick, -1), pf, pm, near


def choose(scene: Scene, options: AutoOptions = AutoOptions()) -> Choice:
    """The variants ``auto`` renders ``scene`` with, and their weights (module docstring)."""
    path = options.auto_table or str(DEFAULT_TABLE)
    f = features(scene)
    centre = np.array([[f["log_alpha"], f["thin"], f["ior"]]])
    pts = _kernel_points(f) if options.auto_blend else centre
    table = load_table(path)
    if not table["scenes"]:
        keys = [("specular" if 10 ** p[0] < SMOOTH_ALPHA else "rousiers", "{}") for p in pts]
        blend = _shares(keys)
        return Choice(blend[0][0], blend[0][1], None, None, (), blend)
    t = _arrays(table)
    # the kernel's points, and the scene's own (last row: the predictions quoted)
    pick, pf, pm, near = _crisp(t, np.concatenate([pts, centre]), options.auto_tolerance)
    if (pick < 0).any():
        raise ConfigError("auto table: the nearest scenes share no measured variant")
    blend = _shares([t.keys[i] for i in pick[:len(pts)]])
    cols = [t.keys.index(_key({"method": m, "options": o})) for m, o, _ in blend]
    w = np.array([b[2] for b in blend])
    return Choice(blend[0][0], blend[0][1], float((w * pf[-1, cols]).sum()),
                  float(pm[-1, cols].sum()), tuple(t.names[i] for i in near[-1]), blend)


def _shares(keys: list[tuple[str, str]]) -> tuple[tuple[str, dict, float], ...]:
    """(method, options, weight) from the kernel points' picks: each variant's share of the
    points, less BLEND_MIN (at most half the largest share), renormalized; largest first."""
    names, counts = np.unique(np.array([json.dumps(k) for k in keys]), return_counts=True)
    order = np.argsort(-counts, kind="stable")
    names, shares = names[order], counts[order] / len(keys)
    w = np.maximum(shares - min(BLEND_MIN, 0.5 * shares[0]), 0.0)
    keep = w > 0
    w = w[keep] / w[keep].sum()
    return tuple((k[0], json.loads(k[1]), float(wi))
                 for k, wi in zip((json.loads(n) for n in names[keep]), w))


def _kernel_points(f: dict[str, float]) -> np.ndarray:
    """(P, 3) feature points of the blend's box kernel around a scene's features: alpha on
    u = asinh(alpha / BLEND_A0) (linear near 0, logarithmic above BLEND_A0; negative alpha
    counts as 0), IOR around the scene's (at least 1), the scene's thinness."""
    na, ni = BLEND_POINTS
    ga = (np.arange(na) + 0.5) / na * 2 - 1  # bin centres in [-1, 1]
    gi = (np.arange(ni) + 0.5) / ni * 2 - 1
    u = np.arcsinh(f["alpha"] / BLEND_A0) + BLEND_HALF_WIDTH[0] * ga
    a = np.maximum(BLEND_A0 * np.sinh(u), 0.0)
    n = np.maximum(f["ior"] + BLEND_HALF_WIDTH[1] * gi, 1.0)
    aa, nn = np.meshgrid(a, n, indexing="ij")
    return np.stack([np.log10(np.maximum(aa.ravel(), ALPHA_FLOOR)),
                     np.full(aa.size, f["thin"]), nn.ravel()], 1)


class Auto:
    """The ``auto`` policy: per scene, the variants to render and their weights."""

    name = "auto"
    Options = AutoOptions

    def parse(self, options: dict | None, source: str | None = None) -> AutoOptions:
        return parse_options(AutoOptions, options, source, self.name)

    def resolve(self, scenes, options: AutoOptions) -> list[Choice]:
        """One :class:`Choice` per scene (its ``blend``: (method, options, weight))."""
        return [choose(s, options) for s in scenes]


POLICY = Auto()

__all__ = ["POLICY", "AutoOptions", "Choice", "choose", "features", "load_table"]
