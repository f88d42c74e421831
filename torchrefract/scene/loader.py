"""The strict scene loader: YAML (or plain data) -> a checked :class:`Scene`.

Unknown keys, wrong types, NaN, out-of-range values and missing files raise
:class:`~torchrefract.checks.ConfigError` naming the file, the key and the value. The
method's name and options are checked against the method registry (which imports no
method until one is used).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from torchrefract.checks import (
    ConfigError,
    check_choice,
    check_file,
    check_keys,
    check_number,
    check_vector,
    load_yaml_file,
    where,
)
from torchrefract.methods import registry
from torchrefract.scene.model import Camera, EnvMap, Material, Scene, SphereLight, Transform

_TOP_KEYS = ("mesh", "transform", "material", "envmap", "lights", "camera", "method",
             "method_options", "exposure", "name")


def _resolve_path(value: Any, key: str, base_dir: Path, source: str | None) -> str:
    return check_file(value, key, base_dir, source)


def scene_from_dict(data: Any, base_dir: str | Path = ".", source: str | None = None,
                    name: str | None = None) -> Scene:
    """Build a validated :class:`Scene` from plain data (a parsed YAML mapping).

    Args:
        data: the mapping, in the form of SCENE_SPEC.md.
        base_dir: directory that relative paths are resolved against.
        source: file name used in error messages.
        name: output stem; defaults to ``data['name']`` or ``"scene"``.

    Raises:
        ConfigError: naming the file, key and value of the first problem found.
    """
    base = Path(base_dir)
    check_keys(data, "", _TOP_KEYS, source, required=("mesh", "envmap"))
    mesh = _resolve_path(data["mesh"], "mesh", base, source)

    t = {} if data.get("transform") is None else data["transform"]
    check_keys(t, "transform", ("scale", "rotate_deg", "translate"), source)
    transform = Transform(
        scale=check_number(t.get("scale", 1.0), "transform.scale", source, minimum=0.0,
                           min_inclusive=False),
        rotate_deg=check_vector(t.get("rotate_deg", [0, 0, 0]), "transform.rotate_deg", source),
        translate=check_vector(t.get("translate", [0, 0, 0]), "transform.translate", source),
    )

    m = {} if data.get("material") is None else data["material"]
    check_keys(m, "material", ("ior", "roughness", "distribution", "roughness_map",
                               "roughness_range", "absorption"), source)
    rmap = m.get("roughness_map")
    rrange = check_vector(m.get("roughness_range", [0.02, 0.5]), "material.roughness_range",
                          source, length=2, minimum=0.0)
    if rrange[1] < rrange[0]:
        raise ConfigError(f"{where(source, 'material.roughness_range')}: expected [lo, hi] "
                          f"with lo <= hi, got {list(rrange)}")
    material = Material(
        ior=check_number(m.get("ior", 1.5), "material.ior", source, minimum=0.0,
                         min_inclusive=False),
        roughness=check_number(m.get("roughness", 0.1), "material.roughness", source,
                               minimum=0.0),
        distribution=check_choice(m.get("distribution", "beckmann"), "material.distribution",
                                  ("beckmann", "ggx"), source),
        roughness_map=None if rmap is None else _resolve_path(rmap, "material.roughness_map",
                                                              base, source),
        roughness_range=rrange,
        absorption=check_vector(m.get("absorption", [0, 0, 0]), "material.absorption", source,
                                minimum=0.0),
    )

    e = data["envmap"]
    if isinstance(e, str):  # shorthand: envmap: path.exr
        e = {"path": e}
    check_keys(e, "envmap", ("path", "scale", "rotate_deg"), source, required=("path",))
    envmap = EnvMap(
        path=_resolve_path(e["path"], "envmap.path", base, source),
        scale=check_number(e.get("scale", 1.0), "envmap.scale", source, minimum=0.0),
        rotate_deg=check_number(e.get("rotate_deg", 0.0), "envmap.rotate_deg", source),
    )

    lights_data = [] if data.get("lights") is None else data["lights"]
    if not isinstance(lights_data, list):
        raise ConfigError(f"{where(source, 'lights')}: expected a list, got {lights_data!r}")
    lights = []
    for i, ld in enumerate(lights_data):
        k = f"lights[{i}]"
        check_keys(ld, k, ("position", "radius", "radiance"), source,
                   required=("position", "radius", "radiance"))
        lights.append(SphereLight(
            position=check_vector(ld["position"], f"{k}.position", source),
            radius=check_number(ld["radius"], f"{k}.radius", source, minimum=0.0,
                                min_inclusive=False),
            radiance=check_vector(ld["radiance"], f"{k}.radiance", source, minimum=0.0),
        ))

    c = {} if data.get("camera") is None else data["camera"]
    check_keys(c, "camera", ("eye", "target", "up", "yfov_deg", "width", "height",
                             "samples_per_pixel"), source)
    camera = Camera(
        eye=check_vector(c.get("eye", [0, 0, 4]), "camera.eye", source),
        target=check_vector(c.get("target", [0, 0, 0]), "camera.target", source),
        up=check_vector(c.get("up", [0, 1, 0]), "camera.up", source),
        yfov_deg=check_number(c.get("yfov_deg", 40.0), "camera.yfov_deg", source, minimum=0.0,
                              min_inclusive=False, maximum=179.0),
        width=check_number(c.get("width", 256), "camera.width", source, minimum=1,
                           integer=True, maximum=16384),
        height=check_number(c.get("height", 256), "camera.height", source, minimum=1,
                            integer=True, maximum=16384),
        samples_per_pixel=check_number(c.get("samples_per_pixel", 1),
                                       "camera.samples_per_pixel", source, minimum=1,
                                       integer=True, maximum=16),
    )
    _check_camera_geometry(camera, source)

    method = check_choice(data.get("method", "specular"), "method", registry.method_names(),
                          source)
    opts = {} if data.get("method_options") is None else data["method_options"]
    check_keys(opts, "method_options", list(opts.keys()) if isinstance(opts, dict) else [],
               source)
    registry.get(method).parse(opts, source)  # raises ConfigError naming the bad option
    exposure = check_number(data.get("exposure", 0.0), "exposure", source)
    nm = data.get("name", name if name is not None else "scene")
    if not isinstance(nm, str) or not nm or "/" in nm or nm.startswith("."):
        raise ConfigError(f"{where(source, 'name')}: expected a file stem, got {nm!r}")
    return Scene(mesh=mesh, envmap=envmap, transform=transform, material=material,
                 lights=tuple(lights), camera=camera, method=method,
                 method_options=dict(opts), exposure=exposure, name=nm)


def _check_camera_geometry(cam: Camera, source: str | None) -> None:
    f = [t - e for t, e in zip(cam.target, cam.eye)]
    nf = math.sqrt(sum(x * x for x in f))
    if nf == 0.0:
        raise ConfigError(f"{where(source, 'camera.target')}: equals camera.eye {list(cam.eye)}")
    cross = [f[1] * cam.up[2] - f[2] * cam.up[1], f[2] * cam.up[0] - f[0] * cam.up[2],
             f[0] * cam.up[1] - f[1] * cam.up[0]]
    nu = math.sqrt(sum(x * x for x in cam.up))
    if math.sqrt(sum(x * x for x in cross)) <= 1e-9 * nf * max(nu, 1e-30):
        raise ConfigError(f"{where(source, 'camera.up')}: {list(cam.up)} is zero or parallel "
                          f"to the view direction {f}")


def load_scene(path: str | Path) -> Scene:
    """Load and validate one scene YAML file (SCENE_SPEC.md form).

    Relative paths inside the file are resolved against the file's directory; the scene's
    ``name`` (output stem) is the file's stem unless the file sets ``name``.

    Raises:
        ConfigError: on a missing file, bad YAML or any invalid value (file and key named).
    """
    p = Path(path)
    data = load_yaml_file(p, "scene")
    return scene_from_dict(data, base_dir=p.parent, source=str(p), name=p.stem)


def validate(scene: Scene) -> Scene:
    """A scene built in Python checked like a loaded file.

    Raises:
        ConfigError: naming the scene and the key, as for a YAML file.
    """
    return scene_from_dict(scene.to_dict(), source=f"scene {scene.name!r}", name=scene.name)
