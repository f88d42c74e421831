"""Method ``auto``: per scene, the cheapest method whose measured error on similar scenes is
within a tolerance of the best one (issue #4, part 6).

The measurements are the speed/accuracy chart's (``scripts/pareto.py`` ->
``outputs/pareto/results.csv``), condensed by ``scripts/build_auto_table.py`` into a table
shipped with the package (``torchrefract/tables/auto_v1.json``): for every suite scene its
features and, for each of our method variants, the time per frame and the FLIP against full
Mitsuba truth (object pixels). For a new scene:

1. Features, from the scene alone (no render needed): roughness alpha (a roughness map: the
   middle of its range), IOR, and thinness, the ratio of the smallest to the largest
   principal extent of the mesh's surface (area-weighted; a slab ~0.1, a sphere 1).
2. Similar scenes: the two nearest suite scenes in (log10 alpha / 0.5, thinness / 0.2,
   IOR / 0.5) space, weighted by inverse distance.
3. For each variant, the predicted FLIP and time are those weighted means; ``auto`` picks the
   fastest variant whose predicted FLIP is at most ``auto_tolerance`` above the best
   predicted FLIP (so a tolerance of 0 asks for the most accurate; a loose one for the
   fastest). Thin objects end up on cheap variants, because that is what the chart
   measured there.
4. A smooth surface needs no cone: below ``SMOOTH_ALPHA`` only ``specular``'s variants are
   candidates (the rough methods' lobes collapse onto its rays there and only add cost and
   the SG fit's own error: on the chart's smooth sphere ``specular`` with 2 bounces has
   FLIP 0.030 at 59 ms, ``rousiers`` with 2 bounces and 4 rays 0.045 at 232 ms). The rule
   holds without a smooth scene in the table, where the nearest measured scenes are rough
   and would favour the rough methods (the leave-one-out check of
   ``scripts/build_auto_table.py``).

Without a table (or with an empty one) a rule stands in: alpha < 0.01 -> ``specular``,
else ``rousiers``. The chosen method and options are written into the result's scenes (and
so into the JSON sidecar of every exported frame).
"""

from __future__ import annotations

import functools
import json
import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ..checks import ConfigError, check_file, check_number, check_option_keys
from ..scene import Scene

DEFAULT_TABLE = Path(__file__).resolve().parent.parent / "tables" / "auto_v1.json"
SCALES = {"log_alpha": 0.5, "thin": 0.2, "ior": 0.5}
SMOOTH_ALPHA = 0.01
"""Roughness below which a surface is smooth: ``specular`` only (module docstring, 4.)."""


@dataclass(frozen=True)
class AutoOptions:
    """Settings of ``auto`` (``method_options`` in a scene)."""

    auto_tolerance: float = 0.05
    """FLIP (object pixels, against full truth) allowed above the most accurate variant."""
    auto_table: str | None = None
    """Path of a table built by ``scripts/build_auto_table.py`` (default: the shipped one)."""

    METHOD = "auto"

    @classmethod
    def from_dict(cls, d: dict, source: str | None = None) -> "AutoOptions":
        check_option_keys(d, [f.name for f in fields(cls)], cls.METHOD, source)
        table = d.get("auto_table")
        if table is not None:
            base = Path(source).parent if source and Path(source).is_file() else Path.cwd()
            table = check_file(table, "method_options.auto_table", base, source)
        return cls(auto_tolerance=check_number(d.get("auto_tolerance", 0.05),
                                               "method_options.auto_tolerance", source,
                                               minimum=0.0, maximum=1.0),
                   auto_table=table)


@dataclass(frozen=True)
class Choice:
    """What ``auto`` picked for a scene and why."""

    method: str
    options: dict
    predicted_flip: float | None
    predicted_ms: float | None
    neighbours: tuple[str, ...]


def features(scene: Scene) -> dict[str, float]:
    """Roughness, IOR and thinness of a scene (see the module docstring)."""
    from ..mesh import load_mesh  # noqa: PLC0415

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
    return {"log_alpha": math.log10(max(alpha, 0.005)), "thin": thin, "ior": float(m.ior)}


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


def choose(scene: Scene, options: AutoOptions = AutoOptions()) -> Choice:
    """The method and options ``auto`` renders ``scene`` with."""
    table = load_table(options.auto_table or str(DEFAULT_TABLE))
    rows = table["scenes"]
    f = features(scene)
    smooth = 10 ** f["log_alpha"] < SMOOTH_ALPHA
    if not rows:
        method = "specular" if smooth else "rousiers"
        return Choice(method, {}, None, None, ())
    dist = np.array([math.sqrt(sum(((f[k] - r["features"][k]) / s) ** 2
                                   for k, s in SCALES.items())) for r in rows])
    near = np.argsort(dist)[:2]
    w = 1.0 / (dist[near] + 1e-3)
    w = w / w.sum()
    # Variants measured on every neighbour, keyed by (method, options).
    keyed = [{(v["method"], json.dumps(v["options"], sort_keys=True)): v
              for v in rows[i]["variants"]} for i in near]
    common = set(keyed[0]).intersection(*keyed[1:])
    if not common:
        raise ConfigError("auto table: the nearest scenes share no measured variant")
    if smooth:  # no cone on a smooth surface (docstring, 4.)
        common = {k for k in common if k[0] == "specular"} or common
    pred = {k: (sum(wi * kv[k]["flip"] for wi, kv in zip(w, keyed)),
                sum(wi * kv[k]["ms"] for wi, kv in zip(w, keyed))) for k in common}
    best = min(p[0] for p in pred.values())
    ok = [k for k, p in pred.items() if p[0] <= best + options.auto_tolerance]
    key = min(ok, key=lambda k: (pred[k][1], pred[k][0]))
    return Choice(key[0], json.loads(key[1]), float(pred[key][0]), float(pred[key][1]),
                  tuple(rows[i]["name"] for i in near))


def render_auto(*_args, **_kwargs):
    """``auto`` is resolved per scene in :func:`torchrefract.render` (it picks another
    method); it has no shading of its own."""
    raise ConfigError("method 'auto' is resolved by torchrefract.render, not called directly")


__all__ = ["AutoOptions", "Choice", "choose", "features", "load_table"]
