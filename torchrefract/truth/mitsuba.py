"""Ground truth: a :class:`~torchrefract.scene.model.Scene` rendered by Mitsuba 3.

The conversion follows SCENE_SPEC.md exactly, because the spec's conventions *are* Mitsuba 3's:

- camera: ``perspective`` sensor, ``fov_axis: y``, ``fov = yfov_deg``,
  ``to_world = look_at(eye, target, up)``; ``hdrfilm`` with a ``box`` reconstruction filter
  and ``pixel_format: rgba`` (alpha = object coverage);
- integrator: ``path`` (``volpath`` when ``material.absorption`` is nonzero, with an interior
  ``homogeneous`` medium of ``sigma_t = absorption`` and albedo 0), ``max_depth`` 64 by
  default and Russian roulette switched off (``rr_depth > max_depth``);
- mesh: a ``mi.Mesh`` filled in Python from :func:`torchrefract.geometry.mesh.load_mesh`, i.e. the
  same world-space vertices, faces and *our* per-vertex shading normals (and UVs), so both
  renderers shade with identical normals;
- material: ``dielectric`` when ``roughness == 0``, else ``roughdielectric`` (``beckmann`` or
  ``ggx``, ``alpha = max(roughness, 1e-4)``), ``int_ior = ior``, ``ext_ior = 1``; with a
  ``roughness_map``, ``roughdielectric`` whose ``alpha`` is a raw, bilinear, repeating
  ``bitmap`` texture of ``lo + v (hi - lo)`` over the mesh UVs (see :func:`_alpha_map`);
- environment: ``envmap`` with ``filename``, ``scale`` and ``to_world = rotate(+Y, rotate_deg)``;
- sphere lights: ``sphere`` shapes with an ``area`` emitter of the given radiance and a black
  ``diffuse`` BSDF (they reflect nothing and hide what lies behind them).

Variant: ``llvm_ad_rgb`` when Debian's ``libllvm19`` is installed
(``/usr/lib/x86_64-linux-gnu/libLLVM-19.so``; ``DRJIT_LIBLLVM_PATH`` is pointed at it before
drjit is imported: the libLLVM 15 that Mesa installs aborts the process in llvm variants),
otherwise ``scalar_rgb`` (always works, slower). The environment variable
``TORCHREFRACT_MI_VARIANT`` forces a variant. Mitsuba is imported lazily, on first use.

Example:
    >>> import torchrefract as tr
    >>> from torchrefract.truth.mitsuba import render_reference
    >>> scene = tr.load_scene("configs/demo.yaml")                    # doctest: +SKIP
    >>> radiance, alpha = render_reference(scene, spp=64)              # doctest: +SKIP
    >>> radiance.shape, alpha.shape                                    # doctest: +SKIP
    ((256, 256, 3), (256, 256))
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from torchrefract.geometry.mesh import load_mesh
from torchrefract.scene.model import Scene

#: Shared libraries of Debian's ``libllvm19`` that drjit's LLVM backend works with.
LIBLLVM19_CANDIDATES = ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
                        "/usr/lib/x86_64-linux-gnu/libLLVM-19.so.1",
                        "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1")

_INSTALL_HINT = ("the Mitsuba 3 reference renderer needs the optional dependencies: "
                 "pip install 'torchrefract[reference]'")

_mi: Any = None  # the mitsuba module once a variant is set
_variant: str = ""  # the variant this module set


def choose_variant() -> str:
    """The Mitsuba variant :func:`mitsuba` will use (does not import mitsuba).

    ``TORCHREFRACT_MI_VARIANT`` when set; else ``llvm_ad_rgb`` when a libLLVM 19 is found
    (or ``DRJIT_LIBLLVM_PATH`` is already set by the user); else ``scalar_rgb``.
    """
    forced = os.environ.get("TORCHREFRACT_MI_VARIANT", "").strip()
    if forced:
        return forced
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return "llvm_ad_rgb"
    if any(Path(p).is_file() for p in LIBLLVM19_CANDIDATES):
        return "llvm_ad_rgb"
    return "scalar_rgb"


def mitsuba():
    """Import Mitsuba 3 (once), set the variant of :func:`choose_variant`, return the module.

    Raises:
        ImportError: Mitsuba is not installed (with the pip command that installs it), or the
            variant is not available in the installed build.
    """
    global _mi, _variant
    if _mi is not None:
        if _mi.variant() != _variant:  # someone else switched the (process-global) variant
            _mi.set_variant(_variant)
        return _mi
    variant = choose_variant()
    if not variant.endswith("_rgb"):
        raise ImportError(f"TORCHREFRACT_MI_VARIANT={variant!r}: torchrefract's reference "
                          "needs an RGB variant (llvm_ad_rgb, scalar_rgb, cuda_ad_rgb)")
    if variant.startswith("llvm") and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        lib = next((p for p in LIBLLVM19_CANDIDATES if Path(p).is_file()), None)
        if lib is not None:  # must happen before drjit initializes its LLVM backend
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    try:
        import mitsuba as mi  # noqa: PLC0415
    except ImportError as exc:
        raise ImportError(f"{_INSTALL_HINT} ({exc})") from exc
    if variant not in mi.variants():
        raise ImportError(f"Mitsuba variant {variant!r} (TORCHREFRACT_MI_VARIANT) is not in "
                          f"this build; available: {mi.variants()}")
    mi.set_variant(variant)
    _mi, _variant = mi, variant
    return mi


def _is_jit(mi) -> bool:
    return not mi.variant().startswith("scalar")


# --------------------------------------------------------------------------------------
# Scene conversion
# --------------------------------------------------------------------------------------

def _mitsuba_mesh(mi, scene: Scene, bsdf, interior=None):
    """A ``mi.Mesh`` holding exactly torchrefract's world-space mesh, normals and UVs."""
    md = load_mesh(scene.mesh, scene.transform)
    v = md.vertices.numpy().astype(np.float32)  # (V, 3)
    f = md.faces.numpy().astype(np.uint32)  # (F, 3)
    n = md.normals.numpy().astype(np.float32)  # (V, 3)
    props = mi.Properties()
    props["bsdf"] = bsdf
    if interior is not None:
        props["interior"] = interior
    mesh = mi.Mesh("glass", len(v), len(f), props=props, has_vertex_normals=True,
                   has_vertex_texcoords=md.uvs is not None)
    params = mi.traverse(mesh)

    def put(key: str, arr: np.ndarray) -> None:
        params[key] = type(params[key])(np.ascontiguousarray(arr).ravel())

    put("vertex_positions", v)
    put("faces", f)
    put("vertex_normals", n)
    if md.uvs is not None:
        # Mitsuba's bitmap textures put v = 0 on the image's top row and its PLY/OBJ loaders
        # flip v on load (flip_tex_coords); doing the same keeps the OpenGL convention of
        # SCENE_SPEC.md (v = 0 at the bottom of the image).
        uv = md.uvs.numpy().astype(np.float32).copy()  # (V, 2)
        uv[:, 1] = 1.0 - uv[:, 1]
        put("vertex_texcoords", uv)
    params.update()
    return mesh


def _alpha_map(scene: Scene) -> dict | float:
    """The roughness map as Mitsuba's ``alpha``: a ``bitmap`` texture of alpha values.

    SCENE_SPEC.md: a map value v (raw, RGB averaged, read by
    :func:`torchrefract.optics.textures.load_roughness_map`) means alpha = lo + v (hi - lo). The
    affine map is applied to the texels (it commutes with bilinear filtering), clamped to
    1e-4 like a constant alpha, and handed over as a one-channel float32 ``mi.Bitmap`` with
    ``raw`` (no sRGB decoding), bilinear filtering and ``repeat`` wrapping. Mitsuba's bitmap
    puts v = 0 on the image's top row with texel centers at (c + 0.5) / W, (r + 0.5) / H;
    :func:`_mitsuba_mesh` hands the mesh's UVs over with v flipped, so each point looks up
    the same texel as :func:`torchrefract.optics.textures.sample_uv` (verified texel by texel in
    tests/test_reference_mitsuba.py). A mesh without UVs reads the map at UV (0, 0)
    everywhere in our methods (the G-buffer's UVs are zero), so it gets that constant alpha
    here too (Mitsuba would otherwise use its own surface parameterization).
    """
    import torch  # noqa: PLC0415

    from torchrefract.optics.textures import load_roughness_map, sample_uv  # noqa: PLC0415

    m = scene.material
    lo, hi = (float(x) for x in m.roughness_range)
    tex = load_roughness_map(m.roughness_map)  # (H, W) raw values in [0, 1]
    if load_mesh(scene.mesh, scene.transform).uvs is None:
        v0 = float(sample_uv(tex, torch.zeros(2)))
        return max(lo + v0 * (hi - lo), 1e-4)
    alpha = np.maximum(lo + tex.numpy().astype(np.float64) * (hi - lo), 1e-4)  # (H, W)
    bitmap = mitsuba().Bitmap(np.ascontiguousarray(alpha[..., None], dtype=np.float32))
    return {"type": "bitmap", "bitmap": bitmap, "raw": True, "filter_type": "bilinear",
            "wrap_mode": "repeat"}


def _bsdf_dict(scene: Scene) -> dict:
    m = scene.material
    if m.ior == 1.0:  # index-matched: no interface at all (Mitsuba's dielectrics reject
        # equal indices); a null BSDF still bounds the interior medium (absorption)
        return {"type": "null"}
    if m.roughness_map is not None:  # SCENE_SPEC.md: the map replaces `roughness`
        return {"type": "roughdielectric", "distribution": m.distribution,
                "alpha": _alpha_map(scene), "int_ior": float(m.ior), "ext_ior": 1.0}
    if m.roughness == 0.0:
        return {"type": "dielectric", "int_ior": float(m.ior), "ext_ior": 1.0}
    return {"type": "roughdielectric", "distribution": m.distribution,
            "alpha": max(float(m.roughness), 1e-4), "int_ior": float(m.ior), "ext_ior": 1.0}


def _clip_range(scene: Scene) -> tuple[float, float]:
    """Near/far clip covering the mesh and lights (Mitsuba's defaults are 1e-2 and 1e4)."""
    eye = np.asarray(scene.camera.eye, np.float64)
    c, r = load_mesh(scene.mesh, scene.transform).bounding_sphere()
    spheres = [(c, r)] + [(np.asarray(l.position, np.float64), l.radius) for l in scene.lights]
    near_gap = min(float(np.linalg.norm(eye - p)) - rad for p, rad in spheres)
    far = max(float(np.linalg.norm(eye - p)) + rad for p, rad in spheres)
    near = 1e-2 if near_gap > 2e-2 else max(1e-6, 0.5 * near_gap) if near_gap > 0 else 1e-6
    return near, max(1e4, 4.0 * far)


def _interior(mi, absorption) -> Any:
    """The glass's absorbing medium (a loaded ``homogeneous`` medium), or None without
    absorption.

    sigma_t as an RGB "reflectance" must lie in [0, 1]: it stores absorption / max and puts
    the max into the medium's scale. Albedo 0: pure Beer-Lambert absorption. A channel of
    exactly 0 makes volpath return NaN (free-flight sampling in that channel never ends;
    measured with Mitsuba 3.9.1), so channels are floored at 1e-7 of the largest: a
    transmittance error of at most 1e-7 * max(absorption) * path length."""
    absorption = np.asarray(absorption, np.float64)
    if not absorption.max() > 0.0:
        return None
    amax = float(absorption.max())
    rel = np.maximum(absorption / amax, 1e-7)
    return mi.load_dict({"type": "homogeneous", "sigma_t": {"type": "rgb", "value": rel.tolist()},
                         "scale": amax, "albedo": 0.0})


def to_mitsuba_dict(scene: Scene, spp: int = 64, seed: int = 0, max_depth: int = 64) -> dict:
    """Convert a scene into a Mitsuba 3 scene dictionary (for ``mi.load_dict``).

    The mesh is included as a ready ``mi.Mesh`` object built from
    :func:`torchrefract.geometry.mesh.load_mesh` (world-space vertices, faces, our vertex normals and
    UVs), so shading normals are identical in both renderers. Imports Mitsuba (and sets its
    variant) if that has not happened yet.

    Args:
        scene: the scene (SCENE_SPEC.md).
        spp: samples per pixel of the ``independent`` sampler.
        seed: sampler seed.
        max_depth: longest path (Mitsuba's ``max_depth``; 3 = front reflection plus two
            refractions). Russian roulette is disabled (``rr_depth = max_depth + 1``).

    Returns:
        A dict with keys ``integrator``, ``sensor``, ``envmap``, ``glass`` and ``light_<k>``.

    Raises:
        ImportError: Mitsuba is not installed.

    Example:
        >>> d = to_mitsuba_dict(scene, spp=16)                     # doctest: +SKIP
        >>> img = mitsuba().render(mitsuba().load_dict(d))         # doctest: +SKIP
    """
    if max_depth < 1:
        raise ValueError(f"max_depth must be >= 1, got {max_depth}")
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    mi = mitsuba()
    T = mi.ScalarTransform4f
    cam = scene.camera
    bsdf = mi.load_dict(_bsdf_dict(scene))
    interior = _interior(mi, scene.material.absorption)
    integrator = {"type": "volpath" if interior is not None else "path",
                  "max_depth": int(max_depth), "rr_depth": int(max_depth) + 1,
                  "hide_emitters": False}

    near, far = _clip_range(scene)
    d: dict[str, Any] = {
        "type": "scene",
        "integrator": integrator,
        "sensor": {
            "type": "perspective",
            "fov": float(cam.yfov_deg),
            "fov_axis": "y",
            "near_clip": near,
            "far_clip": far,
            "to_world": T().look_at(origin=list(map(float, cam.eye)),
                                    target=list(map(float, cam.target)),
                                    up=list(map(float, cam.up))),
            "film": {"type": "hdrfilm", "width": int(cam.width), "height": int(cam.height),
                     "rfilter": {"type": "box"}, "pixel_format": "rgba",
                     "component_format": "float32"},
            "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
        },
        "envmap": {
            "type": "envmap",
            "filename": str(Path(scene.envmap.path).resolve()),
            "scale": float(scene.envmap.scale),
            "to_world": T().rotate(axis=[0.0, 1.0, 0.0], angle=float(scene.envmap.rotate_deg)),
        },
        "glass": _mitsuba_mesh(mi, scene, bsdf, interior),
    }
    for k, light in enumerate(scene.lights):
        d[f"light_{k}"] = {
            "type": "sphere",
            "center": list(map(float, light.position)),
            "radius": float(light.radius),
            "emitter": {"type": "area",
                        "radiance": {"type": "rgb", "value": list(map(float, light.radiance))}},
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
        }
    return d


def render_reference(scene: Scene, spp: int = 64, seed: int = 0, max_depth: int = 64
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Path-trace a scene with Mitsuba 3 (ground truth when converged).

    Two Mitsuba renders: the radiance of :func:`to_mitsuba_dict`, and a coverage pass. With
    a visible environment map Mitsuba's film alpha is 1 on every pixel (every camera ray
    "hits" the environment), so the object coverage comes from a second, cheap render of the
    glass mesh alone (no emitters, two bounces, same sensor, spp and seed), whose alpha is
    the fraction of the pixel's samples that hit the mesh: SCENE_SPEC.md's A channel
    (lights excluded, as in :func:`torchrefract.render`).

    Args:
        scene: the scene (SCENE_SPEC.md).
        spp: samples per pixel (independent random samples, box filter).
        seed: sampler seed.
        max_depth: longest path; 64 (default) is the spec's truth, 3 is the light that a
            two-interface method models (front reflection plus two refractions).

    Returns:
        radiance: (H, W, 3) float32 linear RGB, background included.
        alpha: (H, W) float32 object coverage in [0, 1].

    Raises:
        ImportError: Mitsuba is not installed.
    """
    mi = mitsuba()
    mscene = mi.load_dict(to_mitsuba_dict(scene, spp=spp, seed=seed, max_depth=max_depth))
    img = np.array(mi.render(mscene), dtype=np.float32)  # (H, W, 4)
    cov = np.array(mi.render(mi.load_dict(_coverage_dict(scene, spp, seed))),
                   dtype=np.float32)  # (H, W, 4)
    return np.ascontiguousarray(img[..., :3]), np.ascontiguousarray(cov[..., 3])


def _coverage_dict(scene: Scene, spp: int, seed: int) -> dict:
    """Sensor and glass mesh only, emitters hidden: the render's alpha is mesh coverage."""
    d = to_mitsuba_dict(scene, spp=spp, seed=seed, max_depth=1)
    keep = ("type", "sensor", "glass")
    d = {k: v for k, v in d.items() if k in keep}
    # max_depth 2, not 1: scalar_rgb's path integrator stops at depth 1 before it marks the
    # ray as valid (alpha 0 everywhere); llvm_ad_rgb gives the same alpha either way.
    d["integrator"] = {"type": "path", "max_depth": 2, "hide_emitters": True}
    return d


def eval_envmap_at_pixel_centers(scene: Scene) -> np.ndarray:
    """Mitsuba's own environment radiance along the camera ray of every pixel center.

    Builds the scene's Mitsuba sensor and ``envmap`` emitter, samples the sensor's ray at
    film position ((i + 0.5) / W, (j + 0.5) / H) for column i and row j (aperture sample
    (0.5, 0.5), time 0, wavelength sample 0.5) and evaluates the emitter for a surface
    interaction with ``wi = -ray.d``. This isolates the camera and environment conventions
    from any light transport (vectorized in JIT variants; a loop per pixel in scalar ones).

    Args:
        scene: the scene; only ``camera`` and ``envmap`` are used.

    Returns:
        (H, W, 3) float32 radiance, row 0 at the top.
    """
    mi = mitsuba()
    d = to_mitsuba_dict(scene, spp=1)
    sensor = mi.load_dict(d["sensor"])
    emitter = mi.load_dict(d["envmap"])
    w, h = scene.camera.width, scene.camera.height
    ii, jj = np.meshgrid(np.arange(w), np.arange(h), indexing="xy")  # (H, W) each
    fx = ((ii + 0.5) / w).astype(np.float32).ravel()
    fy = ((jj + 0.5) / h).astype(np.float32).ravel()
    if _is_jit(mi):
        import drjit as dr  # noqa: PLC0415

        ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5),
                                   mi.Point2f(mi.Float(fx), mi.Float(fy)),
                                   mi.Point2f(0.5, 0.5))
        si = dr.zeros(mi.SurfaceInteraction3f, len(fx))
        si.wi = -ray.d
        out = np.array(emitter.eval(si), dtype=np.float32)  # (3, H*W)
        return np.ascontiguousarray(out.T.reshape(h, w, 3))
    out = np.empty((h * w, 3), np.float32)
    for k in range(h * w):
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(float(fx[k]), float(fy[k])),
                                   mi.Point2f(0.5, 0.5))
        si = mi.SurfaceInteraction3f()
        si.wi = -ray.d
        out[k] = np.array(emitter.eval(si), dtype=np.float32).ravel()
    return out.reshape(h, w, 3)
