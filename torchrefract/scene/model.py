"""Scene model: nested frozen dataclasses mirroring SCENE_SPEC.md.

One :class:`Scene` describes one image. Every field has a default except ``mesh`` and
``envmap.path``. The strict loader (:mod:`torchrefract.scene.loader`) builds and checks them.

Example:
    >>> import torchrefract as tr
    >>> scene = tr.load_scene("configs/demo.yaml")           # doctest: +SKIP
    >>> scene = tr.Scene(mesh="assets/meshes/spot.ply",
    ...                  envmap=tr.EnvMap(path="assets/envmaps/studio_small_03.exr"))  # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Transform:
    """Object-to-world transform, applied scale -> rotate -> translate."""

    scale: float = 1.0
    """Uniform scale (> 0)."""
    rotate_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Degrees about world X, then world Y, then world Z (R = Rz @ Ry @ Rx)."""
    translate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """World translation."""


@dataclass(frozen=True)
class Material:
    """Walter et al. 2007 rough dielectric (Mitsuba 3 ``roughdielectric``)."""

    ior: float = 1.5
    """Index of refraction inside the object; outside is 1.0."""
    roughness: float = 0.1
    """Microfacet alpha; 0 means perfectly smooth."""
    distribution: str = "beckmann"
    """``beckmann`` or ``ggx``."""
    roughness_map: str | None = None
    """Optional grayscale image over the mesh UVs (value v in [0, 1])."""
    roughness_range: tuple[float, float] = (0.02, 0.5)
    """v maps to alpha = lo + v * (hi - lo)."""
    absorption: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Beer-Lambert absorption per unit world length inside, linear RGB."""


@dataclass(frozen=True)
class EnvMap:
    """Latitude-longitude HDR environment map (Mitsuba 3 ``envmap`` conventions)."""

    path: str = ""
    """OpenEXR or Radiance .hdr file, linear RGB."""
    scale: float = 1.0
    """Multiplies the radiance."""
    rotate_deg: float = 0.0
    """Rotation of the map about world +Y (right-handed)."""


@dataclass(frozen=True)
class SphereLight:
    """A spherical emitter, seen directly and through the glass; it reflects nothing."""

    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.1
    radiance: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class Camera:
    """Pinhole camera, pixel centers at half integers, row 0 on top."""

    eye: tuple[float, float, float] = (0.0, 0.0, 4.0)
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    yfov_deg: float = 40.0
    """Vertical field of view in degrees."""
    width: int = 256
    height: int = 256
    samples_per_pixel: int = 1
    """Supersampling: n x n sub-pixel samples per pixel, box-filtered."""


@dataclass(frozen=True)
class Scene:
    """One image: a glass mesh under an environment map seen by a pinhole camera."""

    mesh: str
    """Mesh file (anything trimesh loads)."""
    envmap: EnvMap
    transform: Transform = field(default_factory=Transform)
    material: Material = field(default_factory=Material)
    lights: tuple[SphereLight, ...] = ()
    camera: Camera = field(default_factory=Camera)
    method: str = "specular"
    """Which renderer produces the image."""
    method_options: dict = field(default_factory=dict)
    """Settings of that method, e.g. ``{tir: reflect}``."""
    exposure: float = 0.0
    """Extension: exposure in stops applied to the PNG preview only (never to the EXR)."""
    passes: dict = field(default_factory=dict)
    """Extension: optional output passes, name -> options (``matte``, ``flow``;
    :mod:`torchrefract.matte.passes`). Empty: the standard passes only."""
    name: str = "scene"
    """Output file stem (the YAML file's stem when loaded from a file)."""

    def to_dict(self) -> dict:
        """The resolved scene as plain data (for metadata and for writing YAML back)."""
        d = dataclasses.asdict(self)
        d["lights"] = [dict(l) for l in d["lights"]]
        if not d["passes"]:  # not asked for: left out (older records stay the same)
            del d["passes"]
        return d

    def replace(self, **changes: Any) -> "Scene":
        return dataclasses.replace(self, **changes)
