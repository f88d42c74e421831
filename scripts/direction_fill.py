"""A study for `specular`'s adaptive shading (issue #28; docs/benchmarks.md, twenty-sixth
sitting): fill a waiting pixel from its lattice neighbours' exit and reflection directions
(and weights, points), then look the environment up there, instead of from their
radiances. Tensor code only, outside the renderer: `specular` without bounces, each scene's
own view at one sample, its full render's per-pixel paths (``shading.paths.trace_paths``)
and its lattice (``adaptive.lattice``, ``--smooth-alpha`` its roughness floor: the coarse
level first, then the fine one, each filled pixel's means carried on as the renderer's
passes are; no blending).

    .venv/bin/python scripts/direction_fill.py SCENE.yaml [SCENE.yaml ...] [--size 256]
        [--tols 0.05 0.1] [--truth outputs/truth --truth-spp 1024] [--smooth-alpha A]
        [--json OUT.json]

Per scene and rule: the share of object pixels shaded and the FLIP on object pixels
against the full render; with ``--truth``, where the folder holds the scene's cached
Mitsuba truth at this size (``scripts/accuracy.py``'s names), also the FLIP against it,
the full render's beside it. Rules: ``radiance`` (the renderer's test: the neighbours'
spread over their luminance, with the plan's gap), ``direction TOL`` (every neighbour's
exit and reflection direction within TOL radians of their normalized mean, all with
their exit found alike), ``either TOL`` (the direction test, else the radiance test).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import torchrefract as tr  # noqa: E402
from torchrefract.geometry import adaptive  # noqa: E402
from torchrefract.geometry.gbuffer import build_gbuffer  # noqa: E402
from torchrefract.geometry.mesh import load_mesh  # noqa: E402
from torchrefract.lighting.lights import Lighting, incident_radiance  # noqa: E402
from torchrefract.methods.specular import SpecularOptions  # noqa: E402
from torchrefract.optics.materials import MaterialBatch  # noqa: E402
from torchrefract.result import front_roughness  # noqa: E402
from torchrefract.settings import RenderSettings, using  # noqa: E402
from torchrefract.shading.paths import trace_paths  # noqa: E402
from torchrefract.truth.metrics import flip_map  # noqa: E402
from accuracy import truth as cached_truth  # noqa: E402  (the one truth cache)
from pareto import truth_cached  # noqa: E402


def pixel_data(g, lighting, materials) -> dict[str, torch.Tensor]:
    """Per pixel of the (one-view) G-buffer, (H*W, C): what a direction fill interpolates
    (``T`` exit direction, ``R`` reflection, ``W`` transmitted weight with absorption,
    ``F`` reflectance, ``P1``/``P2`` entry and exit points, ``O`` exit found)."""
    with using(RenderSettings(fused=False)):
        paths = trace_paths(g, lighting, materials, SpecularOptions())
    n = g.front.mask.numel()

    def frame(x: torch.Tensor, c: int) -> torch.Tensor:
        out = torch.zeros(n, c)
        out[paths.idx] = x.reshape(-1, c).float()
        return out

    att = torch.exp(-materials.absorption[paths.batch] * paths.path[:, None])
    return {"T": frame(paths.t2, 3), "R": frame(paths.refl, 3),
            "W": frame(paths.e1[:, None] * paths.w2[:, None] * att, 3),
            "F": frame(paths.f1, 1), "P1": frame(paths.p1, 3), "P2": frame(paths.p2, 3),
            "O": frame(paths.found.float(), 1)}


def fill_level(level, w: int, data: dict, rad: torch.Tensor, shaded: torch.Tensor,
               full: torch.Tensor, lighting, rule: str, tol: float) -> None:
    """One level's waiting pixels, in place: filled by ``rule`` or shaded (the full
    render's values); ``data`` carries the means where filled."""
    s = level.frame_stride
    hh, ww = level.status.shape[1:]
    ys, xs = (level.status[0] == 2).nonzero(as_tuple=True)
    fidx = (ys * s) * w + xs * s
    nb, four, _ = adaptive._neighbours(ys * ww + xs, hh, ww)
    fnb = ((nb // ww) * s) * w + (nb % ww) * s
    k = torch.where(four, 4, 2)
    valid = torch.arange(4)[None] < k[:, None]
    fnb = torch.where(valid, fnb, fnb[:, :1])

    def mean(x: torch.Tensor) -> torch.Tensor:
        return (x[fnb] * valid[..., None]).sum(1) / k[:, None]

    def spread(x: torch.Tensor) -> torch.Tensor:
        m = F.normalize(mean(x), dim=-1)
        return torch.acos((x[fnb] * m[:, None]).sum(-1).clamp(-1, 1)).amax(1)

    v, m = rad[fnb], mean(rad)
    rel = (v.amax(1) - v.amin(1)).amax(-1) / (m.sum(-1) / 3 + 1e-3)
    rad_ok = torch.maximum(level.gap[0][ys, xs], rel / adaptive.fill_rtol(level)) < 1
    found = data["O"][fnb][..., 0]
    dir_ok = ((spread(data["T"]) <= tol) & (spread(data["R"]) <= tol)
              & (found == found[:, :1]).all(1))
    if rule == "radiance":
        dir_ok = torch.zeros_like(dir_ok)
    use_rad = ~dir_ok & rad_ok if rule in ("radiance", "either") else torch.zeros_like(dir_ok)
    means = {key: mean(x) for key, x in data.items()}
    if bool(dir_ok.any()):
        bi = torch.zeros(int(dir_ok.sum()), dtype=torch.long)
        l_t = incident_radiance(lighting, bi, means["P2"][dir_ok],
                                F.normalize(means["T"][dir_ok], dim=-1))
        l_r = incident_radiance(lighting, bi, means["P1"][dir_ok],
                                F.normalize(means["R"][dir_ok], dim=-1))
        rad[fidx[dir_ok]] = means["F"][dir_ok] * l_r + means["W"][dir_ok] * l_t
    rad[fidx[use_rad]] = m[use_rad]
    filled = dir_ok | use_rad
    for key, x in data.items():
        x[fidx[filled]] = means[key][filled]
    shaded[fidx[~filled]] = True
    rad[fidx[~filled]] = full[fidx[~filled]]


def truth_image(scene: tr.Scene, folder: Path | None, spp: int):
    """The scene's cached truth (H, W, 3) in ``folder`` (seed 0, max_depth 64: the chart's,
    read through scripts/accuracy.py's cache), or None where it is not there (never
    rendered here)."""
    if folder is None or not truth_cached(scene, spp, folder):
        return None
    return cached_truth(scene, spp, 64, 0, folder)[0]


def study(path: Path, size: int, rules: list[tuple[str, float]],
          truth: Path | None = None, truth_spp: int = 1024,
          smooth_alpha: float = adaptive.SMOOTH_ALPHA) -> list[dict]:
    """Per rule: the share of the view's object pixels shaded, FLIP against the full
    render on them (and against the cached truth where ``truth`` holds it)."""
    s = tr.load_scene(path)
    s = s.replace(camera=dataclasses.replace(s.camera, width=size, height=size,
                                             samples_per_pixel=1), method="specular",
                  method_options={})
    full = tr.render([s], settings=RenderSettings(adaptive=False)).radiance[0]
    g = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    materials, lighting = MaterialBatch.from_scenes([s]), Lighting.from_scenes([s])
    _, lattice = adaptive.lattice(g, front_roughness(g, materials), smooth_alpha=smooth_alpha)
    obj = g.front.mask.reshape(-1)
    ref = truth_image(s, truth, truth_spp)
    on = g.front.mask[0].numpy()
    full_truth = None if ref is None else float(flip_map(full.numpy(), ref)[on].mean())
    paths = pixel_data(g, lighting, materials)  # each rule fills a copy of them
    rows = []
    for rule, tol in rules:
        data = {key: x.clone() for key, x in paths.items()}
        rad, shaded = full.reshape(-1, 3).clone(), obj.clone()
        levels = lattice.levels if lattice is not None else ()
        for level in levels:  # every level's waiting pixels start unshaded
            ys, xs = (level.status[0] == 2).nonzero(as_tuple=True)
            shaded[(ys * level.frame_stride) * size + xs * level.frame_stride] = False
        for level in levels:
            fill_level(level, size, data, rad, shaded, full.reshape(-1, 3), lighting, rule,
                       tol)
        img = rad.view(size, size, 3).numpy()
        row = {"scene": path.stem, "rule": rule, "tol": tol,
               "shaded": float(shaded[obj].float().mean()),
               "flip": float(flip_map(img, full.numpy())[on].mean())}
        if ref is not None:
            row["flip_truth"] = float(flip_map(img, ref)[on].mean())
            row["full_flip_truth"] = full_truth
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--tols", type=float, nargs="+", default=[0.05, 0.1])
    ap.add_argument("--truth", type=Path, help="a folder of cached truth (scripts/accuracy.py)")
    ap.add_argument("--truth-spp", type=int, default=1024)
    ap.add_argument("--smooth-alpha", type=float, default=adaptive.SMOOTH_ALPHA,
                    help="the roughness below which no pixel waits (the renderer's: "
                         f"{adaptive.SMOOTH_ALPHA}; 0: smooth glass waits too)")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args()
    rules = [("radiance", 0.0)] + [(r, t) for t in args.tols for r in ("direction", "either")]
    out = []
    for path in args.scenes:
        for row in study(path, args.size, rules, args.truth, args.truth_spp,
                         args.smooth_alpha):
            out.append(row)
            tol = "" if row["rule"] == "radiance" else f" {row['tol']:g} rad"
            vs_truth = (f"  vs truth {row['flip_truth']:.4f} (full {row['full_flip_truth']:.4f})"
                        if "flip_truth" in row else "")
            print(f"{row['scene']:<20} {row['rule'] + tol:<18} shaded {row['shaded']:.3f}  "
                  f"FLIP vs full {row['flip']:.4f}{vs_truth}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
