"""The validation set: generated scenes, apart from the chart's, split into ``fit`` and ``heldout``.

``generate`` draws ``--count`` (64) scenes from one seeded generator (``--seed``) and writes
them to ``configs/validation/`` (one YAML each, a header comment saying how it was made) with
``splits.json`` (the split and every scene's family and parameters), after writing the
procedural meshes and roughness maps they use (``scripts/validation_meshes.py``). Each scene:

- a mesh: :data:`validation_meshes.FAMILIES` (8 families, every shipped mesh and 30
  procedural ones), the families in equal shares, each family's meshes in turn;
- a pose: a uniform random rotation (shipped scanned models: upright, turned about +Y and
  tilted up to 20 degrees; plates (slab, groove): at least 20 degrees off edge-on),
  a scale (0.6-1.8, log-uniform) and a small translation;
- a material: IOR uniform in [1.1, 2.4]; roughness alpha 0 (smooth) in 12% of the scenes,
  else log-uniform in [0.02, 0.6]; 75% of the scenes whose mesh has UVs take a roughness
  map (a range within [0, 0.6]); Beckmann (as the chart; :data:`P_GGX`); absorption in 1/3
  (transmittance 0.3-0.95 per channel across the object's bounding diameter);
- light: the three environment maps in equal shares, turned at random; a sphere light in
  1/4 (behind the object, or beside it, never between it and the camera);
- the shares above are exact (each a random permutation of the scenes), the continuous
  values drawn per scene;
- a view: orbit azimuth uniform, elevation -15 to 55 degrees, vertical FOV 30-50 degrees,
  distance such that the bounding sphere's disc covers 30-70% of the frame's area;
- 128 x 128 pixels, 2 x 2 supersampling (as the chart's scenes), method ``rousiers``.

Names are ``v<index>_<mesh>_<hash>``: the hash covers the scene and its mesh file, so the
truth cache (keyed by name) never serves an image of another scene after a regeneration.
The split is stratified by family: each family's scenes are shuffled and halved.

    .venv/bin/python scripts/validation_set.py generate [--count 64] [--seed 2026]
    .venv/bin/python scripts/validation_set.py check     # every scene loads and renders
    nice -n 19 .venv/bin/python scripts/validation_set.py truth [--size 128] [--spp 2048]
        [--threads 1] [--noise 8] [--split fit|heldout] [--only NAME ...]

``truth`` renders the converged Mitsuba truth of every scene through ``scripts/accuracy.py``'s
``truth`` (the one truth renderer and cache: ``outputs/truth/<name>_<W>x<H>_d64_spp<spp>_s0.exr``),
skipping what is cached; for ``--noise`` scenes (one per family) also seed 1, and reports the
truth's own noise (seed 1 against seed 0, as ``scripts/truth.py``). Progress (scene k of N,
seconds, ETA) goes to stdout; a scene that fails is recorded and the run goes on. Per-scene
status, times and noise: ``outputs/truth/validation.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import validation_meshes as vm  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CONFIG_DIR = ROOT / "configs" / "validation"
ASSETS = ROOT / "assets"
ENVMAPS = ("lebombo.exr", "rooitou_park.exr", "studio_small_03.exr")
SEED = 2026
COUNT = 64
SIZE = 128
SAMPLES_PER_PIXEL = 2
TRUTH_SPP = 2048
TRUTH_DEPTH = 64
CACHE = ROOT / "outputs" / "truth"
STATUS = "validation.json"
NOISE_KEYS = ("relmse_object", "flip_object", "flip", "hdrflip_object", "psnr_object")

P_SMOOTH = 0.12
P_MAP = 0.75
P_GGX = 0.0
"""Share of GGX scenes: none, as the chart (Beckmann only); the draw is kept (its permutation
is consumed either way), so a share > 0 changes only the scenes it turns to GGX."""
P_ABSORPTION = 1 / 3
P_LIGHT = 0.25
ALPHA_RANGE = (0.02, 0.6)
IOR_RANGE = (1.1, 2.4)
FILL_RANGE = (0.3, 0.7)
MIN_FACING = math.cos(math.radians(70))  # plates: |normal . view| at least this


@dataclasses.dataclass(frozen=True)
class Entry:
    """One generated scene: its file name stem, family, mesh, split and YAML text."""

    name: str
    index: int
    family: str
    mesh: str
    split: str
    text: str
    params: dict


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------

def random_rotation_deg(rng: np.random.Generator) -> list[float]:
    """A uniformly random rotation as SCENE_SPEC's rotate_deg (R = Rz @ Ry @ Rx)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    b = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    a = math.atan2(r[2, 1], r[2, 2])
    c = math.atan2(r[1, 0], r[0, 0])
    return [math.degrees(a), math.degrees(b), math.degrees(c)]


def _dir(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])


def _r(x: float, nd: int = 3) -> float:
    v = round(float(x), nd)
    return 0.0 if v == 0 else v


def _rv(xs, nd: int = 3) -> list[float]:
    return [_r(x, nd) for x in xs]


def draw_flags(rng: np.random.Generator, meshes: list[str]) -> list[dict]:
    """The scenes' discrete choices, in exact shares (a random permutation each): smooth,
    roughness map (of the scenes whose mesh has UVs), GGX, absorption, light, envmap."""
    n = len(meshes)

    def share(p: float, among: np.ndarray) -> set[int]:
        idx = np.flatnonzero(among)
        return set(rng.permutation(idx)[:round(p * len(idx))].tolist())

    uv = np.array([m.endswith(".obj") for m in meshes])
    maps = share(P_MAP, uv)
    smooth = share(P_SMOOTH * n / max(n - len(maps), 1),
                   np.array([i not in maps for i in range(n)]))
    ggx = share(P_GGX, np.ones(n, bool))
    absorption = share(P_ABSORPTION, np.ones(n, bool))
    light = share(P_LIGHT, np.ones(n, bool))
    env = rng.permutation(np.arange(n) % len(ENVMAPS))
    return [{"map": i in maps, "smooth": i in smooth, "ggx": i in ggx,
             "absorption": i in absorption, "light": i in light, "envmap": ENVMAPS[env[i]]}
            for i in range(n)]


def sample_scene(rng: np.random.Generator, family: str, mesh: str, flags: dict
                 ) -> tuple[dict, dict]:
    """One scene's data (SCENE_SPEC.md form, paths relative to configs/validation) and a
    summary of what was drawn; ``flags`` are its discrete choices (:func:`draw_flags`)."""
    from torchrefract.geometry.mesh import load_mesh, rotation_matrix  # noqa: PLC0415
    from torchrefract.scene.model import Transform  # noqa: PLC0415

    mesh_path = ASSETS / "meshes" / mesh
    # Pose and view direction (plates: resampled until the view is off edge-on)
    scale = _r(math.exp(rng.uniform(math.log(0.6), math.log(1.8))))
    for _ in range(1000):
        if family == "model":
            rot = [rng.uniform(-20, 20), rng.uniform(-180, 180), rng.uniform(-20, 20)]
        else:
            rot = random_rotation_deg(rng)
        rot = _rv(rot, 1)
        azimuth, elevation = rng.uniform(-180, 180), rng.uniform(-15, 55)
        view = _dir(azimuth, elevation)  # from the object towards the camera
        if family not in vm.FLAT_FAMILIES:
            break
        normal = rotation_matrix(tuple(rot))[:, 2]  # the plates' thin axis is object z
        if abs(float(normal @ view)) >= MIN_FACING:
            break
    translate = _rv(rng.uniform(-0.3, 0.3, 3))
    transform = Transform(scale=scale, rotate_deg=tuple(rot), translate=tuple(translate))
    center, radius = load_mesh(str(mesh_path), transform).bounding_sphere()
    # Camera: the bounding sphere's disc covers ``fill`` of the (square) frame's area
    yfov = _r(rng.uniform(30, 50), 1)
    fill = rng.uniform(*FILL_RANGE)
    r_img = math.sqrt(4 * fill / math.pi)  # disc radius in units of the frame's half height
    dist = radius / math.sin(math.atan(r_img * math.tan(math.radians(yfov) / 2)))
    target = center + rng.normal(0.0, 0.03 * radius, 3)
    eye = target + dist * view
    # Material
    material: dict = {"ior": _r(rng.uniform(*IOR_RANGE))}
    alpha = math.exp(rng.uniform(*np.log(ALPHA_RANGE)))
    if flags["map"]:
        rmap = vm.ROUGHNESS_MAPS[rng.integers(len(vm.ROUGHNESS_MAPS))]
        lo = rng.uniform(0.0, 0.1)
        hi = rng.uniform(lo + 0.1, ALPHA_RANGE[1])
        material["roughness_map"] = f"../../assets/textures/{rmap}"
        material["roughness_range"] = _rv([lo, hi])
    else:
        material["roughness"] = 0.0 if flags["smooth"] else _r(alpha, 4)
    material["distribution"] = "ggx" if flags["ggx"] else "beckmann"
    trans = rng.uniform(0.3, 0.95, 3)  # across the bounding diameter
    if flags["absorption"]:
        material["absorption"] = _rv(-np.log(trans) / (2 * radius), 4)
    env = {"path": f"../../assets/envmaps/{flags['envmap']}",
           "scale": 1.0, "rotate_deg": _r(rng.uniform(0, 360), 1)}
    lights = []
    if flags["light"]:
        if rng.random() < 0.6:  # behind the object: seen through it
            for _ in range(1000):
                l = -view + rng.normal(0, 0.45, 3)
                l /= np.linalg.norm(l)
                if l @ -view > math.cos(math.radians(50)):
                    break
        else:  # beside or above, never on the camera's side
            for _ in range(1000):
                l = rng.normal(size=3)
                l /= np.linalg.norm(l)
                if l @ view < 0.2 and l[1] > -0.2:
                    break
        lr = radius * rng.uniform(0.08, 0.3)
        pos = center + radius * rng.uniform(1.8, 3.5) * l
        tint = np.array([1.0, rng.uniform(0.75, 1.0), rng.uniform(0.55, 1.0)])
        if rng.random() < 0.3:
            tint = tint[::-1]  # cool instead of warm
        lights.append({"position": _rv(pos), "radius": _r(lr),
                       "radiance": _rv(rng.uniform(3, 15) * tint, 2)})
    data = {
        "mesh": f"../../assets/meshes/{mesh}",
        "transform": {"scale": scale, "rotate_deg": rot, "translate": translate},
        "material": material,
        "envmap": env,
        "lights": lights,
        "camera": {"eye": _rv(eye), "target": _rv(target), "up": [0, 1, 0], "yfov_deg": yfov,
                   "width": SIZE, "height": SIZE, "samples_per_pixel": SAMPLES_PER_PIXEL},
        "method": "rousiers",
    }
    summary = {"ior": material["ior"],
               "roughness": material.get("roughness"),
               "roughness_map": material.get("roughness_map", "").rsplit("/", 1)[-1] or None,
               "roughness_range": material.get("roughness_range"),
               "distribution": material["distribution"],
               "absorption": "absorption" in material, "light": bool(lights),
               "envmap": Path(env["path"]).stem, "fill": round(fill, 3),
               "bounding_radius": round(radius, 3)}
    return data, summary


def _flow(v) -> str:
    """YAML flow style for the values of a scene (numbers, strings without indicators)."""
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_flow(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_flow(x) for x in v) + "]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float, np.floating, np.integer)):
        return repr(v.item() if hasattr(v, "item") else v)
    return str(v)


def scene_yaml(data: dict) -> str:
    lines = []
    for k, v in data.items():
        if k == "lights":
            if v:
                lines.append("lights:")
                lines += [f"  - {_flow(l)}" for l in v]
            continue
        lines.append(f"{k}: {_flow(v)}")
    return "\n".join(lines) + "\n"


def _sha(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()


def build_set(seed: int = SEED, count: int = COUNT) -> list[Entry]:
    """The scenes of one seed (deterministic; reads the mesh files for framing)."""
    import yaml  # noqa: PLC0415

    families = list(vm.FAMILIES)
    rng = np.random.default_rng(seed)
    order = [families[i % len(families)] for i in range(count)]
    rng.shuffle(order)
    mesh_cycle = {f: list(rng.permutation(vm.FAMILIES[f])) for f in families}
    used = {f: 0 for f in families}
    meshes = []
    for fam in order:
        meshes.append(mesh_cycle[fam][used[fam] % len(mesh_cycle[fam])])
        used[fam] += 1
    flags = draw_flags(rng, meshes)
    drafts = []
    for i, (fam, mesh) in enumerate(zip(order, meshes)):
        srng = np.random.default_rng([seed, i])  # the scene's continuous parameters
        data, summary = sample_scene(srng, fam, mesh, flags[i])
        body = scene_yaml(data)
        assert yaml.safe_load(body) == {k: v for k, v in data.items()
                                        if k != "lights" or v}, "YAML round trip"
        h = hashlib.sha1((body + _sha(ASSETS / "meshes" / mesh)).encode()).hexdigest()[:4]
        name = f"v{i:03d}_{Path(mesh).stem}_{h}"
        drafts.append((name, i, fam, mesh, body, summary))
    # the split: each family's scenes shuffled and halved; an odd family's extra scene goes
    # to fit and heldout in turn
    split = {}
    extra = 0
    for fam in families:
        names = [d[0] for d in drafts if d[2] == fam]
        names = [names[j] for j in rng.permutation(len(names))]
        n_fit = len(names) // 2
        if len(names) % 2:
            n_fit += extra
            extra = 1 - extra
        split.update({n: ("fit" if j < n_fit else "heldout") for j, n in enumerate(names)})
    out = []
    for name, i, fam, mesh, body, summary in drafts:
        head = (f"# Validation set: scene {i} of {count} (scripts/validation_set.py generate "
                f"--seed {seed} --count {count})\n"
                f"# family {fam}, mesh {mesh}, split {split[name]}\n")
        out.append(Entry(name, i, fam, mesh, split[name], head + body, summary))
    return out


def noise_scenes(entries: list[Entry]) -> list[str]:
    """One scene per family (its first): the scenes whose truth is also rendered at seed 1."""
    seen, out = set(), []
    for e in entries:
        if e.family not in seen:
            seen.add(e.family)
            out.append(e.name)
    return out


def generate(seed: int = SEED, count: int = COUNT, out_dir: Path = CONFIG_DIR,
             write_meshes: bool = True) -> list[Entry]:
    """Write the meshes, the scenes and splits.json (old generated YAMLs removed)."""
    if write_meshes:
        vm.write_all()
    entries = build_set(seed, count)
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("v*.yaml"):
        old.unlink()
    for e in entries:
        (out_dir / f"{e.name}.yaml").write_text(e.text)
    meta = {
        "how": f"scripts/validation_set.py generate --seed {seed} --count {count}",
        "seed": seed, "count": count,
        "fit": [e.name for e in entries if e.split == "fit"],
        "heldout": [e.name for e in entries if e.split == "heldout"],
        "noise_scenes": noise_scenes(entries),
        "scenes": {e.name: {"index": e.index, "family": e.family, "mesh": e.mesh,
                            "split": e.split, **e.params} for e in entries},
    }
    (out_dir / "splits.json").write_text(json.dumps(meta, indent=1) + "\n")
    return entries


def scene_paths(config_dir: Path = CONFIG_DIR, split: str | None = None) -> list[Path]:
    """The set's YAML files (in index order), optionally of one split."""
    paths = sorted(config_dir.glob("v*.yaml"))
    if split:
        meta = json.loads((config_dir / "splits.json").read_text())
        keep = set(meta[split])
        paths = [p for p in paths if p.stem in keep]
    return paths


# --------------------------------------------------------------------------------------
# Check and truth
# --------------------------------------------------------------------------------------

def set_threads(n: int, mitsuba: bool) -> None:
    """One knob for torch's and drjit's thread pools (0: leave the defaults).

    With a drjit pool of one thread, Mitsuba 3.9's scene loading hangs for good in its EXR
    reader (``Imf::ScanLineInputFile::readPixels`` waits on a semaphore for tasks that the
    pool, reduced to the waiting thread, never runs: seen on the environment map). So
    ``mi.load_dict`` is wrapped to load with two threads (a few ms of work: reading the map)
    and the rendering runs on ``n``.
    """
    if not n:
        return
    import torch  # noqa: PLC0415

    torch.set_num_threads(n)
    if not mitsuba:
        return
    import drjit as dr  # noqa: PLC0415

    from torchrefract.truth.mitsuba import mitsuba as load  # noqa: PLC0415

    mi = load()
    dr.set_thread_count(n)
    if n >= 2 or getattr(mi.load_dict, "_two_thread_load", False):
        return
    load_dict = mi.load_dict

    def two_thread_load(*args, **kwargs):
        dr.set_thread_count(2)
        try:
            return load_dict(*args, **kwargs)
        finally:
            dr.set_thread_count(n)

    two_thread_load._two_thread_load = True
    mi.load_dict = two_thread_load


def check(paths: list[Path]) -> list[dict]:
    """Load and render every scene with ``rousiers`` at its own size; report coverage."""
    import torch  # noqa: PLC0415

    import torchrefract as tr  # noqa: PLC0415

    rows = []
    for p in paths:
        t0 = time.perf_counter()
        try:
            scene = tr.load_scene(p)
            out = tr.render([scene], method="rousiers")
            rad, cov = out.radiance[0], out.coverage[0]
            ok = bool(torch.isfinite(rad).all()) and bool((rad >= 0).all())
            row = {"scene": p.stem, "ok": ok, "coverage": float(cov.mean()),
                   "mean": float(rad[cov > 0.99].mean()) if (cov > 0.99).any() else 0.0}
        except Exception as exc:  # recorded, the check goes on
            row = {"scene": p.stem, "ok": False, "error": f"{type(exc).__name__}: {exc}"}
        row["seconds"] = round(time.perf_counter() - t0, 2)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def _write_status(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.json")
    tmp.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    os.replace(tmp, path)


def run_truth(paths: list[Path], size: int = SIZE, spp: int = TRUTH_SPP, cache: Path = CACHE,
              noise: set[str] = frozenset()) -> dict:
    """Converged truth (seed 0; seed 1 too for ``noise`` scenes) of every scene, cached.

    Returns the status of each scene: render seconds (wall, per seed), CPU seconds (all the
    scene's renders), object coverage, the noise (seed 1 against seed 0) where rendered
    twice, or the error of a scene that failed.
    """
    import torchrefract as tr  # noqa: PLC0415
    from accuracy import truth  # noqa: PLC0415  (the one truth renderer and cache)
    from torchrefract.truth.metrics import compare  # noqa: PLC0415
    from truth import sized  # noqa: PLC0415

    cache.mkdir(parents=True, exist_ok=True)
    status_path = cache / STATUS
    status = json.loads(status_path.read_text()) if status_path.is_file() else {}
    rendered: list[float] = []  # seconds of each scene that needed rendering
    t_start = time.perf_counter()
    n = len(paths)
    for k, p in enumerate(paths):
        t0 = time.perf_counter()
        key = f"{p.stem}_{size}x{size}_spp{spp}"
        entry: dict = {"scene": p.stem, "size": size, "spp": spp, "depth": TRUTH_DEPTH}
        fresh = False
        c0 = time.process_time()  # CPU seconds: what the render costs, however busy the machine
        try:
            scene = sized(tr.load_scene(p), size)
            rgb, alpha, dt = truth(scene, spp, TRUTH_DEPTH, 0, cache)
            secs = {} if math.isnan(dt) else {"s0": round(dt, 2)}
            fresh |= not math.isnan(dt)
            if p.stem in noise:
                rgb2, _, dt2 = truth(scene, spp, TRUTH_DEPTH, 1, cache)
                if not math.isnan(dt2):
                    secs["s1"] = round(dt2, 2)
                    fresh = True
                m = compare(rgb2, rgb, alpha)
                entry["noise"] = {k2: float(m[k2]) for k2 in NOISE_KEYS}
            entry["coverage"] = float((alpha > 0.5).mean())
            entry["render_seconds"] = {**status.get(key, {}).get("render_seconds", {}), **secs}
            if fresh:
                entry["cpu_seconds"] = round(time.process_time() - c0, 2)
            elif "cpu_seconds" in status.get(key, {}):
                entry["cpu_seconds"] = status[key]["cpu_seconds"]
            entry["ok"] = True
        except Exception as exc:  # a broken scene is recorded; the run goes on
            traceback.print_exc()
            entry.update(ok=False, error=f"{type(exc).__name__}: {exc}")
        status[key] = entry
        _write_status(status_path, status)
        dt_scene = time.perf_counter() - t0
        if fresh:
            rendered.append(dt_scene)
        left = n - k - 1
        # the median scene so far: robust to a render that waited (a stopped or starved
        # process on a shared machine) and to the odd slow scene
        eta = left * float(np.median(rendered)) if rendered else 0.0
        what = ("FAILED " + entry["error"]) if not entry["ok"] else \
            ("cached" if not fresh else f"{dt_scene:.1f} s")
        noise_s = (f", noise FLIP {entry['noise']['flip_object']:.3f} relMSE "
                   f"{entry['noise']['relmse_object']:.4f}") if "noise" in entry else ""
        print(f"[{k + 1}/{n}] {p.stem}: {what}{noise_s} | elapsed "
              f"{(time.perf_counter() - t_start) / 60:.1f} min, ETA {eta / 60:.1f} min",
              flush=True)
    failed = [v["scene"] for k2, v in status.items() if not v.get("ok")
              and k2.endswith(f"_{size}x{size}_spp{spp}")]
    print(f"done: {n} scenes, {len(rendered)} rendered in "
          f"{sum(rendered) / 60:.1f} min, {len(failed)} failed {failed}; {status_path}")
    return status


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="write the meshes, scenes and splits.json")
    g.add_argument("--count", type=int, default=COUNT)
    g.add_argument("--seed", type=int, default=SEED)
    g.add_argument("--out", default=str(CONFIG_DIR))
    c = sub.add_parser("check", help="load and render every scene with rousiers")
    t = sub.add_parser("truth", help="render and cache the converged Mitsuba truth")
    t.add_argument("--size", type=int, default=SIZE)
    t.add_argument("--spp", type=int, default=TRUTH_SPP)
    t.add_argument("--noise", type=int, default=8,
                   help="how many scenes also get seed 1: the noise_scenes of splits.json "
                        "(one per family) first, then the others in order")
    t.add_argument("--cache", default=str(CACHE))
    for s in (c, t):
        s.add_argument("--threads", type=int, default=1, help="torch/drjit threads (0: all)")
        s.add_argument("--split", choices=("fit", "heldout"), default=None)
        s.add_argument("--only", nargs="*", default=None, help="scene names (stems)")
        s.add_argument("--dir", default=str(CONFIG_DIR), help="the set's directory")
    args = ap.parse_args()
    if args.cmd == "generate":
        entries = generate(args.seed, args.count, Path(args.out))
        fams = {f: sum(e.family == f for e in entries) for f in vm.FAMILIES}
        print(f"wrote {len(entries)} scenes to {args.out} ({fams}); "
              f"fit {sum(e.split == 'fit' for e in entries)}, "
              f"heldout {sum(e.split == 'heldout' for e in entries)}")
        return
    paths = scene_paths(Path(args.dir), args.split)
    if args.only:
        paths = [p for p in paths if p.stem in set(args.only)]
    set_threads(args.threads, mitsuba=args.cmd == "truth")
    if args.cmd == "check":
        rows = check(paths)
        bad = [r["scene"] for r in rows if not r["ok"]]
        print(f"{len(rows) - len(bad)} of {len(rows)} scenes render; failed: {bad}")
        return
    meta = json.loads((Path(args.dir) / "splits.json").read_text())
    # the noise scenes (one per family) first, then every other scene in order
    order = meta["noise_scenes"] + [p.stem for p in scene_paths(Path(args.dir))
                                    if p.stem not in meta["noise_scenes"]]
    noise = set(order[:args.noise])
    run_truth(paths, args.size, args.spp, Path(args.cache), noise)


if __name__ == "__main__":
    main()
