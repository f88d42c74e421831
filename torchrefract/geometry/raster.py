"""Visibility passes: per-pixel triangle ids of the front and back layers, rasterized with
OpenGL on the EGL context pyrender creates (Mesa's llvmpipe on a CPU), or by the native
rasterizer (csrc/raster.c: both layers of every view of a batch in one call, with these
passes' matrices, vertex snapping, fill rule and depth order; no EGL context), as
``RenderSettings.rasterizer`` picks (:func:`visibility_layers`). The OpenGL passes below
are the reference and the fallback.

pyrender has no id buffer, no integer readback and no back-face pass (DESIGN.md), so the
passes draw directly on its context: one small shader writes ``gl_PrimitiveID + 1`` into a
32-bit integer renderbuffer (0 = background), depth-tested (24-bit depth, as pyrender's
framebuffer), single-sample; the mesh stays resident (a vertex array per mesh, kept for the
last few meshes), and a pass is one draw and one readback of the ids. The back layer draws
the faces with reversed winding under back-face culling, which keeps the nearest back face.
The vertex transform is pyrender's (``P V M inst_m``, the same matrices), so the ids are
those its own forward pass gave (tests/test_gbuffer.py), in less time (docs/decisions.md).
Where the context lacks what this needs (OpenGL 3.3, integer renderbuffers), each pass
renders through pyrender's own forward pass instead (flat vertex colors encoding the id,
``RenderFlags.FLAT``), with one warning. One EGL context per process is created lazily and
reused.
"""

from __future__ import annotations

import math
import os
import threading
from collections import OrderedDict
from contextlib import contextmanager

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchrefract import settings  # noqa: E402
from torchrefract.geometry.camera import camera_frame_floats, camera_pose  # noqa: E402
from torchrefract.geometry.mesh import MeshData  # noqa: E402
from torchrefract.kernels import native  # noqa: E402
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


def _view_matrices(cam: Camera, sphere) -> tuple[np.ndarray, np.ndarray, float, float]:
    """pyrender's projection (``PerspectiveCamera.get_projection_matrix``) and view matrix
    for ``cam``, and their near and far planes, from the mesh's bounding sphere: only the
    ids are used, so depth precision only matters for telling overlapping surfaces
    apart."""
    center, radius = sphere
    eye, r, u, f = camera_frame_floats(cam)
    dist = math.dist(eye, tuple(float(c) for c in center))
    znear = max(dist - radius, 0.0) * 0.5
    # relative to the mesh's size (an absolute floor clipped a mesh of size 1e-7 whole);
    # 1e-30 only for a mesh of one point
    znear = max(znear, radius * 1e-4, 1e-30)
    zfar = dist + radius * 2.0 + znear
    a, t = cam.width / cam.height, math.tan(math.radians(cam.yfov_deg) / 2.0)
    proj = np.zeros((4, 4))
    proj[0][0], proj[1][1], proj[3][2] = 1.0 / (a * t), 1.0 / t, -1.0
    proj[2][2] = (zfar + znear) / (znear - zfar)
    proj[2][3] = (2 * zfar * znear) / (znear - zfar)
    # the inverse of camera_pose's rigid [r u -f | eye]: rows r, u, -f and -R^T eye (in
    # Python floats: numpy's inverse of a 4x4 cost ~0.1 ms a view between kernels)
    rows = [(*v, -math.fsum(x * e for x, e in zip(v, eye))) for v in (r, u, tuple(-x for x in f))]
    return proj, np.array([*rows, (0.0, 0.0, 0.0, 1.0)]), znear, zfar


def view_projection(cam: Camera, sphere) -> np.ndarray:
    """(4, 4) float64 ``P V`` of :func:`_view_matrices`: world to clip space, as the OpenGL
    passes transform (their near and far planes from the mesh's bounding sphere)."""
    proj, view, _, _ = _view_matrices(cam, sphere)
    return proj @ view


_VERTEX = """#version 330 core
layout(location = 0) in vec3 position;
uniform mat4 P;
uniform mat4 V;
uniform mat4 M;
uniform mat4 inst_m;
void main() { gl_Position = P * V * M * inst_m * vec4(position, 1); }
"""
_FRAGMENT = """#version 330 core
layout(location = 0) out int id;
void main() { id = gl_PrimitiveID + 1; }
"""


class _GLMesh:
    """A mesh resident on the context: its vertices and two index buffers (the faces, and
    reversed for the back layer), in one vertex array."""

    def __init__(self, gl, mesh: MeshData):
        self.mesh = mesh  # held, so the cache key (its id) cannot be reused
        self.sphere = mesh.bounding_sphere()
        verts = np.ascontiguousarray(mesh.vertices.numpy(), dtype=np.float32)
        faces = mesh.faces.numpy().astype(np.uint32)
        self.count = int(faces.size)
        self.vao = gl.glGenVertexArrays(1)
        self.buffers = gl.glGenBuffers(3)
        gl.glBindVertexArray(self.vao)
        gl.glBindBuffer(gl.GL_ARRAY_BUFFER, self.buffers[0])
        gl.glBufferData(gl.GL_ARRAY_BUFFER, verts.nbytes, verts, gl.GL_STATIC_DRAW)
        gl.glEnableVertexAttribArray(0)
        gl.glVertexAttribPointer(0, 3, gl.GL_FLOAT, gl.GL_FALSE, 12, None)
        for buf, f in zip(self.buffers[1:], (faces, faces[:, ::-1])):
            f = np.ascontiguousarray(f)
            gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, buf)
            gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, f.nbytes, f, gl.GL_STATIC_DRAW)
        gl.glBindVertexArray(0)

    def delete(self, gl) -> None:
        gl.glDeleteVertexArrays(1, [self.vao])
        gl.glDeleteBuffers(3, self.buffers)


class _GLPasses:
    """The id passes' program, framebuffer (resized as passes ask) and resident meshes."""

    KEPT = 4

    def __init__(self):
        from OpenGL import GL  # noqa: PLC0415
        from OpenGL.GL import shaders  # noqa: PLC0415

        self.gl = GL
        self.program = shaders.compileProgram(
            shaders.compileShader(_VERTEX, GL.GL_VERTEX_SHADER),
            shaders.compileShader(_FRAGMENT, GL.GL_FRAGMENT_SHADER), validate=False)
        self.uniforms = {k: GL.glGetUniformLocation(self.program, k)
                         for k in ("P", "V", "M", "inst_m")}
        self.fbo = GL.glGenFramebuffers(1)
        self.rbo = GL.glGenRenderbuffers(2)
        self.size = None
        self.meshes: OrderedDict[int, _GLMesh] = OrderedDict()

    def _resize(self, w: int, h: int) -> None:
        gl = self.gl
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self.fbo)
        if self.size != (w, h):
            for rb, fmt, att in ((self.rbo[0], gl.GL_R32I, gl.GL_COLOR_ATTACHMENT0),
                                 (self.rbo[1], gl.GL_DEPTH_COMPONENT24,
                                  gl.GL_DEPTH_ATTACHMENT)):
                gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, rb)
                gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, fmt, w, h)
                gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, att, gl.GL_RENDERBUFFER, rb)
            if gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER) != gl.GL_FRAMEBUFFER_COMPLETE:
                self.size = None
                raise RuntimeError(f"the id framebuffer of {w}x{h} is incomplete")
            self.size = (w, h)

    def _mesh(self, mesh: MeshData) -> _GLMesh:
        m = self.meshes.get(id(mesh))
        if m is None or m.mesh is not mesh:
            if m is not None:
                m.delete(self.gl)
            m = _GLMesh(self.gl, mesh)
            self.meshes[id(mesh)] = m
            while len(self.meshes) > self.KEPT:
                self.meshes.popitem(last=False)[1].delete(self.gl)
        self.meshes.move_to_end(id(mesh))
        return m

    def ids(self, mesh: MeshData, cam: Camera, w: int, h: int, back: bool) -> np.ndarray:
        """(h, w) int32 ids + 1 of the nearest front (back) face, row 0 at the top."""
        gl = self.gl
        m = self._mesh(mesh)
        self._resize(w, h)
        proj, view, _, _ = _view_matrices(cam, m.sphere)
        gl.glUseProgram(self.program)
        for name, mat in (("P", proj), ("V", view), ("M", np.eye(4)), ("inst_m", np.eye(4))):
            gl.glUniformMatrix4fv(self.uniforms[name], 1, gl.GL_TRUE, mat.astype(np.float32))
        gl.glViewport(0, 0, w, h)
        gl.glDisable(gl.GL_SCISSOR_TEST)
        gl.glDisable(gl.GL_BLEND)
        gl.glDisable(gl.GL_MULTISAMPLE)
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDepthFunc(gl.GL_LESS)
        gl.glDepthMask(gl.GL_TRUE)
        gl.glDepthRange(0.0, 1.0)
        gl.glEnable(gl.GL_CULL_FACE)
        gl.glCullFace(gl.GL_BACK)
        gl.glFrontFace(gl.GL_CCW)
        gl.glClearBufferiv(gl.GL_COLOR, 0, np.zeros(4, np.int32))
        gl.glClearDepth(1.0)
        gl.glClear(gl.GL_DEPTH_BUFFER_BIT)
        gl.glBindVertexArray(m.vao)
        gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, m.buffers[2 if back else 1])
        gl.glDrawElements(gl.GL_TRIANGLES, m.count, gl.GL_UNSIGNED_INT, None)
        out = np.empty((h, w), dtype=np.int32)
        gl.glReadPixels(0, 0, w, h, gl.GL_RED_INTEGER, gl.GL_INT, out)
        gl.glBindVertexArray(0)
        return out[::-1]


_gl_passes: _GLPasses | None = None
_gl_failed: str | None = None


def _forget_meshes() -> None:
    """Drop every mesh kept on the context (both paths; call under _lock)."""
    _pass_scenes.clear()
    if _gl_passes is not None:
        while _gl_passes.meshes:
            _gl_passes.meshes.popitem()[1].delete(_gl_passes.gl)


def _direct_passes(renderer) -> _GLPasses | None:
    """The process's :class:`_GLPasses` on ``renderer``'s context (made current), or
    ``None`` where it cannot be set up (then pyrender's forward pass renders the ids)."""
    global _gl_passes, _gl_failed
    if _gl_failed is not None:
        return None
    renderer._platform.make_current()
    if _gl_passes is None:
        try:
            _gl_passes = _GLPasses()
        except Exception as exc:  # noqa: BLE001  (any GL failure: pyrender's pass instead)
            import warnings  # noqa: PLC0415

            _gl_failed = f"{type(exc).__name__}: {exc}"
            warnings.warn(f"torchrefract: the direct id pass is unavailable on this OpenGL "
                          f"context ({_gl_failed}); using pyrender's forward pass (the same "
                          f"ids, slower)", RuntimeWarning, stacklevel=3)
            return None
    return _gl_passes


def visibility_pass(mesh: MeshData, cam: Camera, supersample: int = 1,
                    back: bool = False, direct: bool = True) -> torch.Tensor:
    """Rasterize per-pixel triangle ids of the nearest front (or back) face.

    Args:
        mesh: world-space mesh.
        cam: the camera.
        supersample: n; the pass is rendered at (n H, n W).
        back: rasterize back faces (reversed winding) instead of front faces.
        direct: draw on the context directly (module docstring); ``False``: through
            pyrender's forward pass (the same ids).

    Returns:
        (n H, n W) int64 face index into ``mesh.faces``, -1 where no face is seen.
    """
    if mesh.num_faces > _MAX_ID:
        raise ValueError(f"mesh has {mesh.num_faces} triangles; the id buffer holds {_MAX_ID}")
    h, w = cam.height * supersample, cam.width * supersample
    with _lock:
        renderer = get_renderer(w, h)
        passes = _direct_passes(renderer) if direct else None
        if passes is not None:
            ids = passes.ids(mesh, cam, w, h, back).astype(np.int64)
        else:
            ids = _pyrender_ids(mesh, cam, renderer, back)
    ids = np.where(ids > mesh.num_faces, 0, ids) - 1  # out-of-range ids cannot occur
    return torch.from_numpy(np.ascontiguousarray(ids))


def _pyrender_ids(mesh: MeshData, cam: Camera, renderer, back: bool) -> np.ndarray:
    """The ids + 1 through pyrender's forward pass (flat vertex colors; call under _lock)."""
    pyrender = _pyrender()
    ps = _pass_scene(mesh)
    _, _, ps.camera.znear, ps.camera.zfar = _view_matrices(cam, ps.sphere)
    ps.camera.yfov, ps.camera.aspectRatio = np.radians(cam.yfov_deg), cam.width / cam.height
    ps.scene.set_pose(ps.camera_node, camera_pose(cam))
    ps.layers[0].is_visible, ps.layers[1].is_visible = not back, back
    with _multisampling_off():
        color, _ = renderer.render(ps.scene, flags=pyrender.RenderFlags.FLAT)
    c = color.astype(np.int64)
    return (c[..., 0] << 16) | (c[..., 1] << 8) | c[..., 2]


def use_native() -> bool:
    """Whether the current settings' ``rasterizer`` draws with the native rasterizer:
    ``native``, or ``auto`` where the native kernels run (``opengl``: never).

    Raises:
        RuntimeError: ``native`` is asked for and the native kernels did not build.
    """
    choice = settings.current().rasterizer
    if choice == "opengl":
        return False
    if native.available():
        return True
    if choice == "native":
        raise RuntimeError("RenderSettings.rasterizer='native': the native kernels are "
                           f"unavailable ({native.failure() or 'turned off'})")
    return False


def native_layers(meshes: list[MeshData], cameras: list[Camera], supersample: int,
                  id_offsets: list[int], rows: tuple[int, int] | None = None,
                  dtype: torch.dtype = torch.int64, sub: native.SubTest | None = None
                  ) -> tuple | None:
    """:func:`visibility_layers` by the native rasterizer (``native.raster_ids``; the same
    arguments and result; ``rows``: only the rows [r0, r1) of the frame; ``sub``: the
    sub-pixel flags too), or ``None`` where it is unavailable. Each distinct mesh object
    is passed once; the planes are those of the OpenGL passes (:func:`view_projection`)."""
    for m in meshes:
        if m.num_faces > _MAX_ID:  # the kernel's 24-bit face index, as the id buffer's
            raise ValueError(f"mesh has {m.num_faces} triangles; the id buffer holds {_MAX_ID}")
    ranges: dict[int, tuple[int, int, int, int]] = {}  # id(mesh) -> its vertex and face range
    spheres: dict[int, tuple[np.ndarray, float]] = {}
    verts, faces = [], []
    nv = nf = 0
    for m in meshes:
        if id(m) not in ranges:
            ranges[id(m)] = (nv, m.vertices.shape[0], nf, m.num_faces)
            spheres[id(m)] = m.bounding_sphere()
            verts.append(m.vertices)
            faces.append(m.faces)
            nv, nf = nv + m.vertices.shape[0], nf + m.num_faces
    views = torch.tensor([ranges[id(m)] + (int(off),) for m, off in zip(meshes, id_offsets)],
                         dtype=torch.int64)
    mvp = torch.from_numpy(np.stack([view_projection(c, spheres[id(m)])
                                     for m, c in zip(meshes, cameras)]))
    c0 = cameras[0]
    return native.raster_ids(verts[0] if len(verts) == 1 else torch.cat(verts),
                             faces[0] if len(faces) == 1 else torch.cat(faces), views, mvp,
                             c0.height * supersample, c0.width * supersample, rows, dtype,
                             sub)


def sub_layers(meshes: list[MeshData], cameras: list[Camera], id_offsets: list[int],
               sub: native.SubTest) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Both layers' int32 ids on the ``sub.n`` x ``sub.n`` sub-pixel grid
    (:func:`visibility_layers`) and their pixels' sub-pixel flags (csrc/subpixels.h):
    made as the native rasterizer draws the ids, else from the ids drawn
    (``native.sub_flags``); None where the kernels are unavailable."""
    if use_native():
        out = native_layers(meshes, cameras, sub.n, id_offsets, dtype=torch.int32, sub=sub)
        if out is not None:
            return out
    ids = visibility_layers(meshes, cameras, sub.n, id_offsets, dtype=torch.int32)
    return ids[0], ids[1], native.sub_flags(ids, sub)


def visibility_layers(meshes: list[MeshData], cameras: list[Camera], supersample: int,
                      id_offsets: list[int], dtype: torch.dtype = torch.int64
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Front and back ids of B views, drawn by the rasterizer the current settings pick
    (:func:`use_native`; the OpenGL passes, :func:`visibility_pass`, otherwise).

    Args:
        meshes, cameras: B views (equal resolutions).
        supersample: n; the ids are drawn at (n H, n W).
        id_offsets: (B,) added to each view's face indices (the batch's global ids).

    Returns:
        front, back: (B, n H, n W) global ids of ``dtype`` (int64, or int32: 4 bytes a
        sub-pixel), -1 where no face is seen.
    """
    if use_native():
        out = native_layers(meshes, cameras, supersample, id_offsets, dtype=dtype)
        if out is not None:
            return out
        if settings.current().rasterizer == "native":
            raise RuntimeError("RenderSettings.rasterizer='native': the native rasterizer "
                               "could not run (a thread or memory was unavailable)")
    fronts, backs = [], []
    for mesh, cam, off in zip(meshes, cameras, id_offsets):
        for back, out in ((False, fronts), (True, backs)):
            ids = visibility_pass(mesh, cam, supersample, back=back)
            out.append(torch.where(ids >= 0, ids + int(off), ids))
    return torch.stack(fronts).to(dtype), torch.stack(backs).to(dtype)
