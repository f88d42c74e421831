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
from collections import OrderedDict
from contextlib import contextmanager

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchrefract.geometry.camera import camera_pose  # noqa: E402
from torchrefract.geometry.mesh import MeshData  # noqa: E402
from torchrefract.scene.model import Camera  # noqa: E402

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
    """Make pyrender's ``glEnable(GL_MULTISAMPLE)`` a no-op for the duration, its
    offscreen framebuffer single-sample, and its readback color-only.

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

    def read_color(self, scene, flags):
        """pyrender's ``_read_main_framebuffer`` without the depth buffer, which the passes
        do not use: its blit, readback and conversion to linear depth (masked numpy
        writes) took about 1 ms of a 256x256 pass. The color is blitted and read as
        pyrender does (same bytes)."""
        w, h = self._main_fb_dims[0], self._main_fb_dims[1]
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
        GL.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, GL.GL_COLOR_BUFFER_BIT, GL.GL_LINEAR)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb)
        buf = GL.glReadPixels(0, 0, w, h, GL.GL_RGB, GL.GL_UNSIGNED_BYTE)
        return np.flip(np.frombuffer(buf, dtype=np.uint8).reshape(h, w, 3), axis=0), None

    original_read = prr.Renderer._read_main_framebuffer
    prr.glEnable = gl_enable
    prr.glRenderbufferStorageMultisample = storage
    prr.Renderer._read_main_framebuffer = read_color
    try:
        yield
    finally:
        prr.glEnable = original
        prr.glRenderbufferStorageMultisample = original_storage
        prr.Renderer._read_main_framebuffer = original_read


def _id_colors(num_faces: int, offset: int) -> np.ndarray:
    """(3F, 4) float32 RGBA vertex colors encoding id + 1 (8 bits per channel)."""
    ids = np.arange(num_faces, dtype=np.int64) + offset + 1
    rgb = np.stack([(ids >> 16) & 255, (ids >> 8) & 255, ids & 255], -1).astype(np.float32)
    rgba = np.concatenate([rgb / 255.0, np.ones((num_faces, 1), np.float32)], -1)
    return np.repeat(rgba, 3, axis=0)


class _PassScene:
    """A mesh's two pass meshes (front winding, and reversed for the back layer) in one
    pyrender scene with its camera, kept between passes: switching the layer or the view
    sets a visibility flag and the camera, and nothing is uploaded again while the renderer
    keeps rendering this scene (pyrender re-uploads only meshes new to its context)."""

    def __init__(self, mesh: MeshData):
        pyrender = _pyrender()
        self.mesh = mesh  # held, so the cache key (its id) cannot be reused
        faces = mesh.faces.numpy()
        verts = mesh.vertices.numpy()
        colors = _id_colors(mesh.num_faces, 0)
        self.scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.0, 0.0, 0.0])
        self.layers = []
        for f in (faces, faces[:, ::-1]):  # front, back (reversed winding)
            prim = pyrender.Primitive(
                positions=verts[f.reshape(-1)], color_0=colors,  # (3F, 3): unshared vertices
                mode=pyrender.GLTF.TRIANGLES,
                material=pyrender.MetallicRoughnessMaterial(
                    baseColorFactor=[1.0, 1.0, 1.0, 1.0], doubleSided=False))
            pm = pyrender.Mesh([prim])
            self.scene.add(pm)
            self.layers.append(pm)
        self.camera = pyrender.PerspectiveCamera(yfov=1.0, znear=0.1, zfar=10.0)
        self.camera_node = self.scene.add(self.camera)
        self.sphere = mesh.bounding_sphere()


_pass_scenes: "OrderedDict[int, _PassScene]" = OrderedDict()
_PASS_SCENES_KEPT = 4


def _pass_scene(mesh: MeshData) -> _PassScene:
    """The cached :class:`_PassScene` of ``mesh`` (the last few meshes; call under _lock)."""
    ps = _pass_scenes.get(id(mesh))
    if ps is None or ps.mesh is not mesh:
        ps = _PassScene(mesh)
        _pass_scenes[id(mesh)] = ps
        while len(_pass_scenes) > _PASS_SCENES_KEPT:
            _pass_scenes.popitem(last=False)
    _pass_scenes.move_to_end(id(mesh))
    return ps


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
    with _lock:
        ps = _pass_scene(mesh)
        center, radius = ps.sphere
        eye = np.asarray(cam.eye, dtype=np.float64)
        dist = float(np.linalg.norm(center - eye))
        # Near/far planes from the bounding sphere: only the ids are used, so depth
        # precision only matters for telling overlapping surfaces apart.
        znear = max(dist - radius, 0.0) * 0.5
        znear = max(znear, radius * 1e-4, 1e-6)
        zfar = dist + radius * 2.0 + znear
        ps.camera.yfov, ps.camera.aspectRatio = np.radians(cam.yfov_deg), cam.width / cam.height
        ps.camera.znear, ps.camera.zfar = znear, zfar
        ps.scene.set_pose(ps.camera_node, camera_pose(cam))
        ps.layers[0].is_visible, ps.layers[1].is_visible = not back, back
        renderer = get_renderer(w, h)
        with _multisampling_off():
            color, _ = renderer.render(ps.scene, flags=pyrender.RenderFlags.FLAT)
    c = color.astype(np.int64)
    ids = (c[..., 0] << 16) | (c[..., 1] << 8) | c[..., 2]
    ids = np.where(ids > mesh.num_faces, 0, ids) - 1  # out-of-range ids cannot occur
    return torch.from_numpy(np.ascontiguousarray(ids))
