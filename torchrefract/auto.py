"""The ``auto`` policy: per scene, the cheapest method variant that does as well as the best
one ("model no more than a scene needs"). It picks methods; it shades nothing itself.

By default (``auto_pass``) the evidence is the scene's own: a cheap first pass
(:mod:`torchrefract.auto_pass`) renders it small with two variants the table names, the
most accurate on average (``accurate``) and the fastest within ``auto_tolerance`` of it on
average (``cheap``). Where their pass images diverge by less than ``DIVERGENCE[0]`` the cheap
variant renders the image, above ``DIVERGENCE[1]`` the accurate one, in between both,
blended linearly in the divergence (continuous in roughness and IOR as the images are);
with ``auto_regions`` (default) in between each renders only on the pixels where it weighs,
weighted per pixel by the pass's local divergence (:mod:`torchrefract.auto_pass`). The
table's neighbours (2. below) still give the prediction recorded with the image.
Without the pass (``auto_pass: false``) the table's neighbours choose, as follows.

The measurements are a speed/accuracy chart's (``scripts/pareto.py``), condensed by
``scripts/build_auto_table.py`` into a table: per measured scene its features and, per
variant, time per frame and FLIP against Mitsuba truth. The shipped table
(``tables/auto_v2.json``) holds the validation set's ``fit`` half (32 generated scenes,
docs/validation.md); ``tables/auto_v1.json`` (the chart's suite scenes) is kept for
``auto_table``. For a scene:

1. Features from the scene alone: roughness alpha (a map: the middle of its range), IOR,
   and thinness (smallest / largest principal extent of the area-weighted surface).
2. The ``NEIGHBOURS`` nearest table scenes in (asinh(alpha / ALPHA_U0) / 1.15, thinness / 0.2,
   IOR / 0.5), weighted by inverse distance, predict each variant's FLIP and time.
3. A candidate is within ``auto_tolerance`` of the best predicted FLIP, and on each of those
   neighbours within ``auto_tolerance`` of what the predicted best measured there (a cheap
   variant that lost badly on one similar scene is not risked); the fastest candidate wins.
4. Below ``SPLIT_MIN_ALPHA`` no variant splits a lobe into rays (``bounce_rays`` > 1): a
   smooth surface has no lobe to split. ``tir: clamp`` is never a candidate (it fails the
   furnace and continuity suites).
5. Blend (``auto_blend``, default): 1.-4. evaluated on a box kernel of ``BLEND_POINTS``
   points around the scene (alpha on u = asinh(alpha / BLEND_A0) +- BLEND_HALF_WIDTH[0],
   IOR +- BLEND_HALF_WIDTH[1]); each variant weighs its share of the points less
   ``BLEND_MIN`` (renormalized) and the image is the weighted sum, so a roughness or IOR
   sweep changes the image continuously instead of jumping where the pick changes.

Without a table a rule stands in for 1.-3. (alpha < SMOOTH_ALPHA: ``specular``, else
``rousiers``). A single pick is recorded as the result's scene, a blend keeps ``auto``; every
share goes to ``RenderResult.blends``, the sidecar JSON and a sweep's manifest. Why each
constant is what it is, and what it was measured to cost: docs/decisions.md ("auto" sections)
and docs/validation.md.
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchrefract.checks import ConfigError
from torchrefract.options import option, parse_options
from torchrefract.scene.model import Scene

DEFAULT_TABLE = Path(__file__).resolve().parent / "tables" / "auto_v2.json"
SCALES = {"u_alpha": 1.15, "thin": 0.2, "ior": 0.5}
"""Feature scales of the distance (docstring, 2.): above ALPHA_U0 a factor ~3 in alpha
(asinh(x) ~ ln(2x): 1.15 = ln(10) / 2), a fifth of the thinness range and half an IOR unit
count alike (other scales and extra features, on the fit half: docs/decisions.md)."""
ALPHA_U0 = 0.05
"""Roughness where the alpha feature turns from linear to logarithmic: a log scale all the
way down put smooth glass as far from alpha 0.025 as 0.025 is from 0.125 (docs/decisions.md)."""
NEIGHBOURS = 6
"""Table scenes a prediction averages (docstring, 2.): fewer follow one scene's noise, more
leave only the costliest variant (the fit half's leave-one-out: docs/decisions.md)."""
SMOOTH_ALPHA = 0.04
"""Roughness below which the table-less rule renders ``specular``. With a table smooth
scenes follow its measurements (on the fit half ``rousiers`` with bounces beat ``specular``
on smooth scenes: docs/decisions.md)."""
SPLIT_MIN_ALPHA = 0.06
"""Roughness below which the table's rule (``auto_pass: false``) lets no variant split a lobe
into rays (docstring, 4.; the first pass needs no such rule: it compares both): four rays step
sharply in alpha near 0 (the continuity suite's suzanne) and gained little there on the fit
half; the blend's kernel ramps them in above it (docs/decisions.md)."""
ALPHA_FLOOR = 0.005
"""``features``' log10 alpha (kept in the tables for reading) is of max(alpha, ALPHA_FLOOR)."""
EXCLUDED_TIR = ("clamp",)
"""Exit rules ``auto`` never picks (module docstring, 4.)."""
SPLIT_OPTION = "bounce_rays"
"""The option whose values above 1 split a lobe into rays (docstring, 4.)."""
BLEND_A0 = 0.1
BLEND_HALF_WIDTH = (0.5, 0.1)
"""The blend's box kernel (module docstring, 5.): half-widths in u = asinh(alpha / BLEND_A0)
and in IOR."""
BLEND_MIN = 0.15
"""Kernel shares below this are not rendered (the others: share - BLEND_MIN, renormalized)."""
BLEND_POINTS = (32, 16)
"""Points of the kernel along u and IOR (shares are multiples of 1 / 512)."""
DIVERGENCE = (0.0175, 0.0325)
"""First pass (module docstring): below the first divergence the cheap variant alone, above
the second the accurate one alone, linear in between. Fitted on the validation set's fit
half (``scripts/fit_auto_pass.py``): the cheapest ramp with no fit scene more than 0.03 FLIP
behind the accurate variant and mean FLIP and time no worse than its, ending at 0.03 or
above (the continuity suite; docs/decisions.md, "`auto`'s first pass")."""


@dataclass(frozen=True)
class AutoOptions:
    """Settings of ``auto`` (``method_options`` in a scene)."""

    auto_tolerance: float = option(0.02, minimum=0.0, maximum=1.0)
    """FLIP (object pixels, against full truth) allowed above the most accurate variant: on
    the table's average for the first pass's cheap variant (docstring, top); without the
    pass on average over the neighbours and on each one (3.)."""
    auto_table: str | None = option(None, path=True)
    """Path of a table built by ``scripts/build_auto_table.py`` (default: the shipped one;
    relative to the scene file)."""
    auto_blend: bool = option(True, boolean=True)
    """Blend the picks around the scene's roughness and IOR, or over the first pass's
    divergence ramp (continuous in both; docstring); ``false``: one variant per scene,
    switching at thresholds."""
    auto_pass: bool = option(True, boolean=True)
    """Choose by a cheap first pass of the scene itself (docstring, top); ``false``: by the
    table's neighbours alone (1.-5.)."""
    auto_regions: bool = option(True, boolean=True)
    """Inside the first pass's ramp, render each variant only on the pixels where it weighs,
    by the pass's local divergence (:mod:`torchrefract.auto_pass`, "Per region"), instead of
    both over the whole object; ``false``: the scene-level blend."""


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
    best_flip: float | None = None
    """The most accurate candidate's predicted FLIP at the scene (``predicted_flip`` is
    within ``auto_tolerance`` of it for a single pick)."""
    tolerance: float | None = None
    divergence: float | None = None
    """The first pass's divergence of the cheap variant's image from the accurate one's (None
    without a pass)."""
    pass_ms: float | None = None
    """The first pass's time, per scene of the batch it ran for."""
    maps: tuple[torch.Tensor, ...] | None = None
    """With ``auto_regions`` inside the ramp: per entry of ``blend`` its (height, width)
    float32 weight per pixel (adding up to 1; a variant renders only where its weight is
    above 0); ``blend``'s weights are then the scene-level ones the maps refine."""

    def record(self) -> dict | None:
        """What ``auto`` predicted, JSON-ready, for the sidecar and the manifest (None
        without a table)."""
        if self.predicted_flip is None:
            return None
        out = {"predicted_flip": self.predicted_flip, "predicted_ms": self.predicted_ms,
               "best_predicted_flip": self.best_flip, "tolerance": self.tolerance,
               "neighbours": list(self.neighbours)}
        if self.divergence is not None:
            out.update(divergence=self.divergence, divergence_ramp=list(DIVERGENCE),
                       pass_ms=self.pass_ms)
        if self.maps is not None:  # per variant of ``blend``: the share of pixels rendered
            out["region_shares"] = [float((m > 0).float().mean()) for m in self.maps]
        return out


def features(scene: Scene) -> dict[str, float]:
    """Roughness, IOR and thinness of a scene (see the module docstring)."""
    m = scene.material
    alpha = m.roughness if m.roughness_map is None else 0.5 * sum(m.roughness_range)
    return {"log_alpha": math.log10(max(alpha, ALPHA_FLOOR)),
            "thin": _thinness(scene.mesh, scene.transform), "ior": float(m.ior),
            "alpha": float(alpha)}


@functools.lru_cache(maxsize=64)
def _thinness(path: str, transform) -> float:
    """Smallest / largest principal extent of a mesh's area-weighted surface (kept per mesh
    and transform: a sweep renders one mesh many times)."""
    from torchrefract.geometry.mesh import load_mesh  # noqa: PLC0415

    mesh = load_mesh(path, transform)
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
    return float(ext.min() / max(ext.max(), 1e-30))


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
    split: np.ndarray  # (V,) bool: splits a lobe into rays (docstring, 4.)
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
    x = np.array([_point(r["features"]) for r in rows]) / np.array(list(SCALES.values()))
    split = np.array([json.loads(k[1]).get(SPLIT_OPTION, 1) not in (1, "1") for k in keys], bool)
    out = _Arrays(tuple(keys), x.reshape(len(rows), len(SCALES)), flip, ms, split,
                  tuple(r["name"] for r in rows))
    _ARRAYS[id(table)] = (table, out)
    return out


def _point(f: dict[str, float]) -> list[float]:
    """A scene's unscaled feature point (u_alpha, thinness, IOR) from :func:`features`."""
    return [math.asinh(max(f["alpha"], 0.0) / ALPHA_U0), f["thin"], f["ior"]]


def _key(v: dict) -> tuple[str, str]:
    return v["method"], json.dumps(v.get("options", {}), sort_keys=True)


def _crisp(t: _Arrays, f: np.ndarray, tolerance: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rule of the module docstring (1.-4.) at P feature points ``f`` (P, 3: u_alpha,
    thinness, IOR; :func:`_point`): per point the picked variant's column (-1: no variant
    measured on every neighbour), every variant's predicted FLIP and time (P, V), the
    (P, k) neighbour rows and the most accurate candidate's predicted FLIP (P,)."""
    x = f / np.array(list(SCALES.values()))
    dist = np.sqrt(((x[:, None, :] - t.x[None]) ** 2).sum(-1))  # (P, S)
    near = np.argsort(dist, axis=1, kind="stable")[:, :NEIGHBOURS]  # (P, k)
    w = 1.0 / (np.take_along_axis(dist, near, 1) + 1e-3)
    w = w / w.sum(1, keepdims=True)
    fn = t.flip[near]  # (P, k, V); NaN where a neighbour lacks a variant
    pf = (w[..., None] * fn).sum(1)  # (P, V); NaN where a neighbour lacks it
    pm = (w[..., None] * t.ms[near]).sum(1)
    ok = np.isfinite(pf) & np.isfinite(pm)
    smooth = ALPHA_U0 * np.sinh(f[:, 0]) < SPLIT_MIN_ALPHA  # no lobe to split (4.)
    whole = ok & ~t.split[None]
    ok = np.where((smooth & whole.any(1))[:, None], whole, ok)
    best_col = np.where(ok, pf, np.inf).argmin(1)  # (P,)
    best = np.take_along_axis(pf, best_col[:, None], 1)
    ok &= pf <= best + tolerance
    # ... and on every neighbour within tolerance of what the predicted best measured there
    ref = np.take_along_axis(fn, best_col[:, None, None].repeat(fn.shape[1], 1), 2)
    ok &= (fn <= ref + tolerance).all(1)
    fastest = np.where(ok, pm, np.inf).min(1, keepdims=True)
    pick = np.where(ok & (pm == fastest), pf, np.inf).argmin(1)  # ties: the more accurate
    return np.where(ok.any(1), pick, -1), pf, pm, near, best[:, 0]


def choose(scene: Scene, options: AutoOptions = AutoOptions()) -> Choice:
    """The variants ``auto`` renders ``scene`` with, and their weights (module docstring)."""
    path = options.auto_table or str(DEFAULT_TABLE)
    f = features(scene)
    centre = np.array([_point(f)])
    pts = _kernel_points(f) if options.auto_blend else centre
    table = load_table(path)
    if not table["scenes"]:
        smooth = ALPHA_U0 * np.sinh(pts[:, 0]) < SMOOTH_ALPHA
        keys = [("specular" if sm else "rousiers", "{}") for sm in smooth]
        blend = _shares(keys)
        return Choice(blend[0][0], blend[0][1], None, None, (), blend)
    t = _arrays(table)
    # the kernel's points, and the scene's own (last row: the predictions quoted)
    pick, pf, pm, near, best = _crisp(t, np.concatenate([pts, centre]),
                                      options.auto_tolerance)
    if (pick < 0).any():
        raise ConfigError("auto table: the nearest scenes share no measured variant")
    blend = _shares([t.keys[i] for i in pick[:len(pts)]])
    cols = [t.keys.index(_key({"method": m, "options": o})) for m, o, _ in blend]
    w = np.array([b[2] for b in blend])
    return Choice(blend[0][0], blend[0][1], float((w * pf[-1, cols]).sum()),
                  float(pm[-1, cols].sum()), tuple(t.names[i] for i in near[-1]), blend,
                  float(best[-1]), float(options.auto_tolerance))


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
    """(P, 3) feature points (:func:`_point`) of the blend's box kernel around a scene: alpha on
    u = asinh(alpha / BLEND_A0) (linear near 0, logarithmic above BLEND_A0; negative alpha
    counts as 0), IOR around the scene's (at least 1), the scene's thinness."""
    na, ni = BLEND_POINTS
    ga = (np.arange(na) + 0.5) / na * 2 - 1  # bin centres in [-1, 1]
    gi = (np.arange(ni) + 0.5) / ni * 2 - 1
    u = np.arcsinh(f["alpha"] / BLEND_A0) + BLEND_HALF_WIDTH[0] * ga
    a = np.maximum(BLEND_A0 * np.sinh(u), 0.0)
    n = np.maximum(f["ior"] + BLEND_HALF_WIDTH[1] * gi, 1.0)
    aa, nn = np.meshgrid(a, n, indexing="ij")
    return np.stack([np.arcsinh(aa.ravel() / ALPHA_U0), np.full(aa.size, f["thin"]),
                     nn.ravel()], 1)


def pass_variants(t: _Arrays, tolerance: float) -> tuple[int, int]:
    """Columns of the first pass's (cheap, accurate) variants: the lowest mean FLIP over the
    table's scenes (variants measured on all of them), and the lowest mean time among those
    within ``tolerance`` of it (the same column when none is faster)."""
    full = np.isfinite(t.flip).all(0) & np.isfinite(t.ms).all(0)
    if not full.any():
        raise ConfigError("auto table: no variant is measured on every scene")
    mf = np.where(full, t.flip.mean(0) if len(t.names) else np.inf, np.inf)
    accurate = int(mf.argmin())
    ok = mf <= mf[accurate] + tolerance
    cheap = int(np.where(ok, t.ms.mean(0), np.inf).argmin())
    return cheap, accurate


def pass_weight(d: float, blend: bool = True) -> float:
    """The cheap variant's weight at first-pass divergence ``d`` (module docstring)."""
    lo, hi = DIVERGENCE
    if not blend:
        return 1.0 if d <= 0.5 * (lo + hi) else 0.0
    if d <= lo or d >= hi:  # exactly one variant: none rendered at a rounding's weight
        return 1.0 if d <= lo else 0.0
    return float((hi - d) / (hi - lo))


def choose_by_pass(scenes: list[Scene], options: AutoOptions = AutoOptions()) -> list[Choice]:
    """The first pass's choices (module docstring, top), or :func:`choose`'s for each scene
    without a table."""
    table = load_table(options.auto_table or str(DEFAULT_TABLE))
    if not table["scenes"]:
        return [choose(s, options) for s in scenes]
    t = _arrays(table)
    cheap, accurate = pass_variants(t, options.auto_tolerance)
    decode = [(t.keys[j][0], json.loads(t.keys[j][1])) for j in (cheap, accurate)]
    maps = [None] * len(scenes)
    if cheap == accurate:
        div, secs = [0.0] * len(scenes), 0.0
    else:
        from torchrefract.auto_pass import divergence_maps  # noqa: PLC0415

        div, maps, secs = divergence_maps(scenes, decode[0], decode[1])
    pts = np.array([_point(features(s)) for s in scenes])
    _, pf, pm, near, _ = _crisp(t, pts, options.auto_tolerance)
    out = []
    for i, d in enumerate(div):
        w = pass_weight(d, options.auto_blend) if cheap != accurate else 1.0
        parts = sorted([(w, 0, cheap), (1.0 - w, 1, accurate)], key=lambda p: (-p[0], p[1]))
        parts = [p for p in parts if p[0] > 0]
        blend = tuple((decode[k][0], decode[k][1], float(wk)) for wk, k, _ in parts)
        cols = [c for _, _, c in parts]
        ws = np.array([wk for wk, _, _ in parts])
        region_maps = None
        if options.auto_regions and len(parts) == 2:
            region_maps = _region_maps(scenes[i], maps[i], 1.0 - w, [k for _, k, _ in parts])
        out.append(Choice(blend[0][0], blend[0][1], float((ws * pf[i, cols]).sum()),
                          float(pm[i, cols].sum()), tuple(t.names[j] for j in near[i]), blend,
                          float(min(pf[i, cheap], pf[i, accurate])),
                          float(options.auto_tolerance), float(d),
                          1000.0 * secs / max(len(scenes), 1), region_maps))
    return out


def _region_maps(scene: Scene, pass_maps, w_accurate: float, order: list[int]
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The (cheap, accurate) variants' per-pixel weights at the scene's pixels, in the
    blend's ``order`` (0 cheap, 1 accurate): :func:`torchrefract.auto_pass.region_weights`."""
    from torchrefract.auto_pass import local_ramp, region_weights  # noqa: PLC0415

    div_map, coverage = pass_maps
    c = scene.camera
    acc = region_weights(local_ramp(div_map, coverage, (c.height, c.width), DIVERGENCE),
                         w_accurate)
    both = (1.0 - acc, acc)
    return tuple(both[k] for k in order)


class Auto:
    """The ``auto`` policy: per scene, the variants to render and their weights."""

    name = "auto"
    Options = AutoOptions

    def parse(self, options: dict | None, source: str | None = None) -> AutoOptions:
        return parse_options(AutoOptions, options, source, self.name)

    def resolve(self, scenes, options: AutoOptions) -> list[Choice]:
        """One :class:`Choice` per scene (its ``blend``: (method, options, weight)): by the
        first pass (``auto_pass``) or by the table's neighbours."""
        if options.auto_pass:
            return choose_by_pass(list(scenes), options)
        return [choose(s, options) for s in scenes]


POLICY = Auto()

__all__ = ["POLICY", "AutoOptions", "Choice", "choose", "choose_by_pass", "features",
           "load_table", "pass_variants", "pass_weight"]
