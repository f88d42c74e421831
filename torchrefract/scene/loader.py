"""The strict scene loader: YAML (or plain data) -> a checked :class:`Scene`.

Unknown keys, wrong types, NaN, out-of-range values and missing files raise
:class:`~torchrefract.checks.ConfigError` naming the file, the key and the value. The
method's name and options are checked against the method registry (which imports no
method until one is used).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections import OrderedDict
from pathlib import Path
from typing import Any

from torchrefract.checks import (
    RADIANCE_LIMIT,
    ConfigError,
    check_choice,
    check_file,
    check_keys,
    check_number,
    check_vector,
    load_yaml_file,
    where,
)
from torchrefract.kept import KeptByIdentity
from torchrefract.matte.passes import parse_passes
from torchrefract.methods import registry
from torchrefract.scene.model import Camera, EnvMap, Material, Scene, SphereLight, Transform

_TOP_KEYS = ("mesh", "transform", "material", "envmap", "lights", "camera", "method",
             "method_options", "exposure", "passes", "name")
NAME_BYTES = 250
"""Longest output stem: its files (``<name>.json``) stay within a file name's 255 bytes."""


def _section(data: dict, key: str) -> dict:
    return {} if data.get(key) is None else data[key]


def _get(d: dict, key: str, cls: type) -> Any:
    """``d[key]``, else the dataclass ``cls``'s default for that field (written once)."""
    return d.get(key, cls.__dataclass_fields__[key].default)


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
    mesh = check_file(data["mesh"], "mesh", base, source)
    transform = _transform(_section(data, "transform"), source)
    material = _material(_section(data, "material"), base, source)
    envmap = _envmap(data["envmap"], base, source)
    lights = _lights([] if data.get("lights") is None else data["lights"], source)
    camera = _camera(_section(data, "camera"), source)
    method = check_choice(_get(data, "method", Scene), "method", registry.method_names(),
                          source)
    opts = _section(data, "method_options")
    check_keys(opts, "method_options", list(opts.keys()) if isinstance(opts, dict) else [],
               source)
    registry.get(method).parse(opts, source)  # raises ConfigError naming the bad option
    exposure = check_number(_get(data, "exposure", Scene), "exposure", source)
    passes = parse_passes(data.get("passes"), source)
    nm = data.get("name", name if name is not None else "scene")
    if (not isinstance(nm, str) or not nm or "/" in nm or "\0" in nm or nm.startswith(".")
            or len(nm.encode("utf-8", "surrogateescape")) > NAME_BYTES):
        raise ConfigError(f"{where(source, 'name')}: expected a file stem (no '/', no NUL, "
                          f"not starting with '.', at most {NAME_BYTES} bytes), got {nm!r}")
    return Scene(mesh=mesh, envmap=envmap, transform=transform, material=material,
                 lights=lights, camera=camera, method=method,
                 method_options=dict(opts), exposure=exposure, passes=passes, name=nm)


def _transform(t: dict, source: str | None) -> Transform:
    check_keys(t, "transform", ("scale", "rotate_deg", "translate"), source)
    return Transform(
        scale=check_number(_get(t, "scale", Transform), "transform.scale", source, minimum=0.0,
                           min_inclusive=False),
        rotate_deg=check_vector(_get(t, "rotate_deg", Transform), "transform.rotate_deg",
                                source),
        translate=check_vector(_get(t, "translate", Transform), "transform.translate", source),
    )


def _material(m: dict, base: Path, source: str | None) -> Material:
    check_keys(m, "material", ("ior", "roughness", "distribution", "roughness_map",
                               "roughness_range", "absorption"), source)
    rmap = m.get("roughness_map")
    rrange = check_vector(_get(m, "roughness_range", Material), "material.roughness_range",
                          source, length=2, minimum=0.0)
    if rrange[1] < rrange[0]:
        raise ConfigError(f"{where(source, 'material.roughness_range')}: expected [lo, hi] "
                          f"with lo <= hi, got {list(rrange)}")
    return Material(
        ior=check_number(_get(m, "ior", Material), "material.ior", source, minimum=0.0,
                         min_inclusive=False),
        roughness=check_number(_get(m, "roughness", Material), "material.roughness", source,
                               minimum=0.0),
        distribution=check_choice(_get(m, "distribution", Material), "material.distribution",
                                  ("beckmann", "ggx"), source),
        roughness_map=None if rmap is None else check_file(rmap, "material.roughness_map",
                                                           base, source),
        roughness_range=rrange,
        absorption=check_vector(_get(m, "absorption", Material), "material.absorption",
                                source, minimum=0.0),
    )


def _envmap(e: Any, base: Path, source: str | None) -> EnvMap:
    if isinstance(e, (str, os.PathLike)):  # shorthand: envmap: path.exr
        e = {"path": e}
    check_keys(e, "envmap", ("path", "scale", "rotate_deg"), source, required=("path",))
    return EnvMap(
        path=check_file(e["path"], "envmap.path", base, source),
        scale=check_number(_get(e, "scale", EnvMap), "envmap.scale", source, minimum=0.0,
                           maximum=RADIANCE_LIMIT),
        rotate_deg=check_number(_get(e, "rotate_deg", EnvMap), "envmap.rotate_deg", source),
    )


def _lights(lights_data: Any, source: str | None) -> tuple[SphereLight, ...]:
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
            radiance=check_vector(ld["radiance"], f"{k}.radiance", source, minimum=0.0,
                                  maximum=RADIANCE_LIMIT),
        ))
    return tuple(lights)


def _camera(c: dict, source: str | None) -> Camera:
    check_keys(c, "camera", ("eye", "target", "up", "yfov_deg", "width", "height",
                             "samples_per_pixel"), source)
    camera = Camera(
        eye=check_vector(_get(c, "eye", Camera), "camera.eye", source),
        target=check_vector(_get(c, "target", Camera), "camera.target", source),
        up=check_vector(_get(c, "up", Camera), "camera.up", source),
        yfov_deg=check_number(_get(c, "yfov_deg", Camera), "camera.yfov_deg", source,
                              minimum=0.0, min_inclusive=False, maximum=179.0),
        width=check_number(_get(c, "width", Camera), "camera.width", source, minimum=1,
                           integer=True, maximum=16384),
        height=check_number(_get(c, "height", Camera), "camera.height", source, minimum=1,
                            integer=True, maximum=16384),
        samples_per_pixel=check_number(_get(c, "samples_per_pixel", Camera),
                                       "camera.samples_per_pixel", source, minimum=1,
                                       integer=True, maximum=16),
    )
    _check_camera_geometry(camera, source)
    return camera


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


def validate(scene: Scene, method: str | None = None) -> Scene:
    """A scene built in Python checked like a loaded file (with ``method`` in place of its
    own where given).

    The last scene objects checked are remembered (by identity, with their two mutable
    fields' contents): a training loop or a benchmark renders the same objects again and
    again, and the check is ~0.4 ms a scene.

    Raises:
        ConfigError: naming the scene and the key, as for a YAML file.
    """
    mutable = repr((method, scene.method_options, scene.passes))
    checked = _validated.get(scene, mutable)
    if checked is None:
        asked = scene if method is None or method == scene.method else scene.replace(
            method=method)
        checked = _validated.put(scene, mutable, _check(asked))
    return checked


def _check(scene: Scene) -> Scene:
    """:func:`validate`'s check of a new scene object. A dataset's scenes are new objects
    that differ from the last ones by their cameras: everything but the camera is checked
    once per value (its repr: every field exact) and only the camera again."""
    source = f"scene {scene.name!r}"
    _check_parts(scene, source)
    rest = repr([(f.name, getattr(scene, f.name)) for f in dataclasses.fields(scene)
                 if f.name != "camera"])
    checked = _checked_rest.get(rest)
    if checked is None:
        checked = scene_from_dict(scene.to_dict(), source=source, name=scene.name)
        _checked_rest[rest] = checked
        while len(_checked_rest) > 64:
            _checked_rest.popitem(last=False)
        return checked
    _checked_rest.move_to_end(rest)
    cam = scene.camera  # its fields by name (no deep copy: _camera only reads them)
    fields = {f.name: getattr(cam, f.name) for f in dataclasses.fields(cam)}
    return dataclasses.replace(checked, camera=_camera(fields, source))


def _check_parts(scene: Scene, source: str) -> None:
    """A Python-built scene's parts are the model's types (a loaded file's always are)."""
    for key, kind in (("camera", Camera), ("material", Material), ("transform", Transform)):
        value = getattr(scene, key)
        if not isinstance(value, kind):
            raise ConfigError(f"{where(source, key)}: expected a torchrefract.{kind.__name__}, "
                              f"got {value!r}")
    if not isinstance(scene.envmap, (EnvMap, str, os.PathLike, type(None))):
        raise ConfigError(f"{where(source, 'envmap')}: expected a torchrefract.EnvMap or a "
                          f"file path, got {scene.envmap!r}")
    lights = scene.lights
    if not isinstance(lights, (list, tuple)) or not all(isinstance(x, SphereLight)
                                                        for x in lights):
        raise ConfigError(f"{where(source, 'lights')}: expected a list of "
                          f"torchrefract.SphereLight, got {lights!r}")


_validated = KeptByIdentity(256)
"""validate's memory: per scene object and (the method asked for, its mutable fields'
repr), the checked scene."""
_checked_rest: OrderedDict[str, Scene] = OrderedDict()
"""_check's memory: the last 64 scenes checked, by the repr of all their fields but the
camera."""
