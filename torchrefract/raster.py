"""Visibility passes with pyrender: per-pixel triangle ids of the front and back layers.

pyrender has no id buffer, no float readback and no back-face pass, so (DESIGN.md):
every triangle gets its own three vertices with a flat vertex color encoding ``id + 1`` in
24 bits (0 = background), rendered with ``RenderFlags.FLAT`` (no lighting, no gamma).
The back layer renders the same triangles with reversed winding under back-face culling,
which keeps the nearest back face. Multisampling must be off or edge pixels blend ids:
pyrender's forward pass calls ``glEnable(GL_MULTISAMPLE)``, which we intercept while our
passes run (and its offscreen framebuffer is made single-sample, which it then need not
be resolved from). One EGL context per process is created lazily and reused.
"""

from __future__ import annotations

import os
import threading
from contextlib import contextmanager

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from .camera import camera_pose  # noqa: E402
from .mesh import MeshData  # noqa: E402
from .scene import Camera  # noqa: E402

_MAX_ID = (1 << 24) - 1
_lock = threading.Lock()
_renderer = None


def _pyrender():
    try:
        import pyrender  # noqa: PLC0415
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise RuntimeError(
            "pyrender could not be imported ({}). Headless rendering needs EGL: install the "
            "Debian packages libegl1 libegl-mesa0 libgl1 (scripts/setup.sh does this) and keep "
            "PYOPENGL_PLATFORM=egl.".format(exc)) from exc
    return pyrender


def get_renderer(width: int, height: int):
    """The process-wide pyrender OffscreenRenderer, resized to (width, height)."""
    global _renderer
    pyrender = _pyrender()
    if _renderer is None:
        try:
            _renderer = pyrender.OffscreenRenderer(width, height)
        except Exception as exc:
            raise RuntimeError(
                f"could not create a headless OpenGL (EGL) context: {exc}. Install libegl1 "
                "libegl-mesa0 libgl1 (scripts/setup.sh) and set PYOPENGL_PLATFORM=egl before "
                "anything imports OpenGL.") from exc
    if (_renderer.viewport_width, _renderer.viewport_height) != (width, height):
        _renderer.viewport_width, _renderer.viewport_height = width, height
    return _renderer


@contextmanager
def _multisampling_off():
    """Make pyrender's ``glEnable(GL_MULTISAMPLE)`` a no-op for the duration, and its
    offscreen framebuffer single-sample.

    pyrender renders offscreen into a 4-sample framebuffer and resolves it by a blit. With
    multisampling disabled every sample of a pixel holds the same id, so the 4 samples only
    cost llvmpipe memory traffic and a resolve: the framebuffer it creates while a pass runs
    (the first pass, and after a resize) gets 0 samples, a plain buffer (the same ids).
    """
    import pyrender.renderer as prr  # noqa: PLC0415
    from OpenGL import GL  # noqa: PLC0415

    original = prr.glEnable
    original_storage = prr.glRenderbufferStorageMultisample

    def gl_enable(cap):
        if cap == GL.GL_MULTISAMPLE:
            GL.glDisable(GL.GL_MULTISAMPLE)
            return None
        return original(cap)

    def storage(target, _samples, fmt, width, height):
        return original_storage(target, 0, fmt, width, height)

    prr.glEnable = gl_enable
    prr.glRenderbufferStorageMultisample = storage
    try:
        yield
    finally:
        prr.glEnable = original
        prr.glRenderbufferStorageMultisample = original_storage


def _id_colors(num_faces: int, offset: int) -> np.ndarray:
    """(3F, 4) float32 RGBA vertex colors encoding id + 1 (8 bits per channel)."""
    ids = np.arange(num_faces, dtype=np.int64) + offset + 1
    rgb = np.stack([(ids >> 16) & 255, (ids >> 8) & 255, ids & 255], -1).astype(np.float32)
    rgba = np.concatenate([rgb / 255.0, np.ones((num_faces, 1), np.float32)], -1)
    return np.repeat(rgba, 3, axis=0)


def visibility_pass(mesh: MeshData, cam: Camera, supersample: int = 1,
                    back: bool = False) -> torch.Tensor:
    """Rasterize per-pixel triangle ids of the nearest front (or back) face.

    Args:
        mesh: world-space mesh.
        cam: the camera.
        supersample: n; the pass is rendered at (n H, n W).
        back: rasterize back faces (reversed winding) instead of front faces.

    Returns:
        (n H, n W) int64 face index into ``mesh.faces``, -1 where no face is seen.
    """
    if mesh.num_faces > _MAX_ID:
        raise ValueError(f"mesh has {mesh.num_faces} triangles; the id buffer holds {_MAX_ID}")
    pyrender = _pyrender()
    h, w = cam.height * supersample, cam.width * supersample
    faces = mesh.faces.numpy()
    if back:
        faces = faces[:, ::-1]
    pos = mesh.vertices.numpy()[faces.reshape(-1)]  # (3F, 3): unshared vertices
    center, radius = mesh.bounding_sphere()
    eye = np.asarray(cam.eye, dtype=np.float64)
    dist = float(np.linalg.norm(center - eye))
    # Near/far planes from the bounding sphere: only the ids are used, so depth precision
    # only matters for telling overlapping surfaces apart.
    znear = max(dist - radius, 0.0) * 0.5
    znear = max(znear, radius * 1e-4, 1e-6)
    zfar = dist + radius * 2.0 + znear

    prim = pyrender.Primitive(
        positions=pos, color_0=_id_colors(mesh.num_faces, 0), mode=pyrender.GLTF.TRIANGLES,
        material=pyrender.MetallicRoughnessMaterial(baseColorFactor=[1.0, 1.0, 1.0, 1.0],
                                                    doubleSided=False))
    scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.0, 0.0, 0.0])
    scene.add(pyrender.Mesh([prim]))
    camera = pyrender.PerspectiveCamera(yfov=np.radians(cam.yfov_deg), znear=znear,
                                        zfar=zfar, aspectRatio=cam.width / cam.height)
    scene.add(camera, pose=camera_pose(cam))
    with _lock:
        renderer = get_renderer(w, h)
        with _multisampling_off():
            color, _ = renderer.render(scene, flags=pyrender.RenderFlags.FLAT)
    c = color.astype(np.int64)
    ids = (c[..., 0] << 16) | (c[..., 1] << 8) | c[..., 2]
    ids = np.where(ids > mesh.num_faces, 0, ids) - 1  # out-of-range ids cannot occur
    return torch.from_numpy(np.ascontiguousarray(ids))
