"""Fused shading: a method's per-pixel work as one native kernel (kernels/csrc/specular.c for
``specular`` and ``prefiltered``, csrc/rousiers.c, csrc/background.c), the one place where a
method's shading chooses between the fused kernel and its tensor code.

The tensor code stays the reference and the differentiable path. A fused kernel runs where
it gives the same image: the native kernels are built (:mod:`.native`), the settings ask
for it (``RenderSettings(fused=True)``, the default), no input wants a gradient, every
tensor is on the CPU, and the kernel covers the scene's features. Today: at most 64 sphere
lights; ``rousiers`` with its default spread (``spread: rays``; either ``cone_rays``),
roughness maps and internal bounces; ``specular`` (internal bounces included)
and ``prefiltered``. Elsewhere these functions return ``None`` and the
method runs its tensor code; tests/test_fused.py holds the two to the same images. A
method whose kernel lives in its own library (``sh``: methods/sh/csrc/sh_shade.c, on this
frame) builds its frame here (:func:`_frame`) and runs through :func:`_run`, as
shading/fused_lean.py does.
"""

from __future__ import annotations

import ctypes
import math

import torch

from torchrefract import settings
from torchrefract.geometry import adaptive
from torchrefract.kept import KeptByIdentity
from torchrefract.kernels import native
from torchrefract.kernels.march import camera_planes
from torchrefract.lighting.lights import _GL_W, _GL_X
from torchrefract.lighting.sg_pyramid import _texel_angle
from torchrefract.matte import record
from torchrefract.optics import microfacet as mf
from torchrefract.optics.exit_rule import TIR_RULES
from torchrefract.optics.sg_table import K_MAX, K_MIN
from torchrefract.optics.sgfit import load_sg_table
from torchrefract.shading.bounces import escape_grid
from torchrefract.stages import stage

_DIST = {"beckmann": 0, "ggx": 1}


def _wants_grad(g, lighting, materials) -> bool:
    if not torch.is_grad_enabled():
        return False
    tensors = [] if materials is None else [materials.ior, materials.roughness,
                                            materials.absorption]
    tensors += [*_lighting_tensors(lighting), g.ray_dir, g.front.position, g.front.normal,
                g.meshes.tri_vertices, g.meshes.tri_normals]
    return any(t.requires_grad for t in tensors)


class _Keep(list):
    """The tensors a job points into, kept alive until the call returns."""

    def ptr(self, t: torch.Tensor, dtype: torch.dtype = torch.float32) -> int:
        t = native.as_input(t).to(dtype)
        self.append(t)
        return t.data_ptr()

    def array(self, tensors) -> ctypes.c_void_p:
        """A C array of the tensors' data pointers (float32, contiguous copies kept; NULL
        for None)."""
        ptrs = [None if t is None else self.ptr(t) for t in tensors]
        a = (ctypes.c_void_p * len(ptrs))(*ptrs)
        self.append(a)
        return ctypes.cast(a, ctypes.c_void_p)


def _runs(g, lighting, materials=None) -> bool:
    """Whether the fused kernels may run for this batch (module docstring)."""
    return (settings.current().fused and g.ray_dir.device.type == "cpu"
            and g.ray_dir.dtype == torch.float32 and not _wants_grad(g, lighting, materials)
            and native.available())


_BUILT = KeptByIdentity(4)
"""The lights' and SG pyramids' structs built per Lighting object (a render pass's, asked
for by the background, the one-sample pass and a sparse pass's samples) and its tensors'
versions, with the tensors they point into: the last two passes' (four entries), so that
at most two passes' maps and pyramids outlive their pass here."""


def _per_lighting(kind: str, lighting, keep: _Keep, build):
    """``build(lighting, keep)``'s struct, built once per ``lighting`` (and its tensors'
    contents), the tensors it points into added to ``keep``."""
    key = (kind, *(t._version for t in _lighting_tensors(lighting)))
    hit = _BUILT.get(lighting, key)
    if hit is None:
        own = _Keep()
        hit = _BUILT.put(lighting, key, (build(lighting, own), own))
    keep.extend(hit[1])
    return hit[0]


def _lights(lighting, keep: _Keep) -> native._Lights:
    """The ``Lights`` of csrc/lighting.h for a batch (:func:`_per_lighting`)."""
    return _per_lighting("lights", lighting, keep, _build_lights)


def _build_lights(lighting, keep: _Keep) -> native._Lights:
    texels = lighting.texels
    # envmap.rotate_y's cosine and sine, one 0-d tensor at a time as it takes them (torch's
    # vectorized and scalar kernels may round differently)
    a = [-r * (math.pi / 180.0) for r in lighting.rotate_deg.detach().float()]
    cos, sin = torch.stack([torch.cos(x) for x in a]), torch.stack([torch.sin(x) for x in a])
    return native._Lights(
        tex=keep.array(texels),
        tex_h=keep.ptr(torch.tensor([t.shape[0] for t in texels]), torch.int64),
        tex_w=keep.ptr(torch.tensor([t.shape[1] for t in texels]), torch.int64),
        rot_cos=keep.ptr(cos), rot_sin=keep.ptr(sin),
        scale=keep.ptr(lighting.scale),
        nl=lighting.light_pos.shape[1], light_pos=keep.ptr(lighting.light_pos),
        light_r=keep.ptr(lighting.light_radius), light_le=keep.ptr(lighting.light_radiance),
        gl_x=keep.ptr(_GL_X, torch.float64), gl_w=keep.ptr(_GL_W, torch.float64),
        gl_n=_GL_X.numel())


def _table(keep: _Keep) -> native._SgTable:
    table = load_sg_table()
    spec = table.spec
    return native._SgTable(
        vol=keep.ptr(table.volume(torch.float32, "cpu")),
        dvol=keep.ptr(table.energy_change_volume(torch.float32, "cpu")),
        vol_l2=keep.ptr(table.volume(torch.float32, "cpu", "l2")),
        evol=keep.ptr(table.energy_volume(torch.float32, "cpu")),
        nt=spec.n_theta, ne=spec.n_eta, na=spec.n_alpha, eta_max=spec.eta_max,
        la0=math.log(spec.alpha_min), la1=math.log(spec.alpha_max), alpha_min=spec.alpha_min,
        alpha_floor=mf.ALPHA_MIN, log_k_min=math.log(K_MIN), log_k_max=math.log(K_MAX))


def background(g, lighting) -> torch.Tensor | None:
    """``shading.background.background``'s (B*H*W, 3) radiance, or ``None`` where the fused
    kernels do not run."""
    if not _runs(g, lighting):
        return None
    b, h, w = g.shape
    keep = _Keep()
    out = torch.empty(b * h * w, 3)
    job = native._BackgroundJob(
        b=b, hw=h * w, ray_dir=keep.ptr(g.ray_dir), eye=keep.ptr(g.eye),
        front_mask=keep.ptr(g.front.mask, torch.bool), front_dist=keep.ptr(g.front.dist),
        lights=_lights(lighting, keep), out=out.data_ptr())
    return out if native._call("background", job) else None


def _sg_meta(pyr) -> torch.Tensor:
    """A pyramid's constants for ``sg_env_tap`` (csrc/lighting.h) as
    ``sg_pyramid._blend_weights`` takes them: the base texel's variance v0, the level
    count, each level's blended sharpness, the atlas rectangles and the sharpnesses (kept
    per pyramid: a batch of views of one map reads the same)."""
    hit = _SG_META.get(pyr)
    if hit is not None:
        return hit
    _, _, h0, w0 = pyr.rects[0]
    v0 = _texel_angle(h0, w0) ** 2 / 6
    ks = torch.tensor(pyr.sharpness[1:], dtype=torch.float32)
    kap = torch.cat([ks.new_tensor([1 / v0]), ks / (1 + v0 * ks), ks.new_zeros(1)])
    meta = torch.cat([torch.tensor([v0, float(len(ks))]), kap,
                      torch.tensor(pyr.rects, dtype=torch.float32).reshape(-1), ks])
    return _SG_META.put(pyr, None, meta)


_SG_META = KeptByIdentity(8)


def _sg_env(lighting, keep: _Keep) -> native._SgEnv:
    """Each view's SG pyramid (``Lighting.pyramid``) for ``sg_env_tap`` and ``sg_env_read``
    in csrc/lighting.h (:func:`_per_lighting`)."""
    return _per_lighting("sg_env", lighting, keep, _build_sg_env)


def _build_sg_env(lighting, keep: _Keep) -> native._SgEnv:
    """:func:`_sg_env`'s struct (a map's pyramid looked up once per batch)."""
    bases, atlases, metas, base_hw, atlas_hw = [], [], [], [], []
    pyramids: dict = {}
    for b in range(len(lighting.texels)):
        key = (lighting.paths[b], id(lighting.texels[b]))  # (an edited map: its own)
        if key not in pyramids:
            pyramids[key] = lighting.pyramid(b)
        pyr = pyramids[key]
        metas.append(_sg_meta(pyr))
        bases.append(pyr.base)
        atlases.append(pyr.atlas)
        base_hw.append(pyr.base.shape[1:])
        atlas_hw.append(pyr.atlas.shape[1:])
    return native._SgEnv(base=keep.array(bases), atlas=keep.array(atlases),
                         meta=keep.array(metas),
                         base_hw=keep.ptr(torch.tensor(base_hw), torch.int64),
                         atlas_hw=keep.ptr(torch.tensor(atlas_hw), torch.int64))


def incident_sg(lighting, batch: torch.Tensor, origin: torch.Tensor, direction: torch.Tensor,
                sharpness: torch.Tensor) -> torch.Tensor | None:
    """``lights.incident_radiance_sg`` (``env: sg``) of N lobes in one kernel call, the fused
    kernels' own lookups (csrc/lighting.h's ``incident_sg``: the same values within float32
    rounding): (N, 3) for lobes of views ``batch`` (N,) int64 at ``origin``, ``direction``
    (N, 3) with ``sharpness`` (N,). ``None`` where it does not run: the fused kernels off or
    unavailable, a gradient wanted, a matte recording (it records the tensor code's
    lookups), or a tensor of another dtype, shape or device."""
    n = batch.shape[0]
    if (not (settings.current().fused and native.available()) or record.active()
            or origin.shape != (n, 3) or direction.shape != (n, 3) or sharpness.shape != (n,)
            or not native.no_grad_through(origin, direction, sharpness,
                                          *_lighting_tensors(lighting))):
        return None
    held = native._inputs((origin, direction, sharpness), (batch,))
    if held is None:
        return None
    out = torch.empty((n, 3), dtype=torch.float32)
    if n == 0:
        return out
    if (not native.views_in_range(batch, len(lighting.texels))
            or bool((~(sharpness >= 0)).any())):  # the tensor code raises its error
        return None
    keep = _Keep()
    o, d, k, bi = held
    job = native._IncidentJob(lights=_lights(lighting, keep), env=_sg_env(lighting, keep),
                              n=n, batch=bi.data_ptr(), o=o.data_ptr(), d=d.data_ptr(),
                              k=k.data_ptr(), out=out.data_ptr())
    return out if native._call("incident_sg", job) else None


def front_lobes(view: torch.Tensor, n1: torch.Tensor, cos1: torch.Tensor, ior: torch.Tensor,
                alpha: torch.Tensor, dist: torch.Tensor):
    """``lobes.front_lobes`` (step 1, eqs. 8-9) of N points in one kernel call, the fused
    kernels' own table lookups (csrc/rousiers.c's ``lobes``: the same values within float32
    rounding), as a ``FrontLobes``; ``None`` where it does not run (as
    :func:`incident_sg`)."""
    from torchrefract.methods.rousiers.lobes import FrontLobes  # noqa: PLC0415

    n = cos1.shape[0]
    out = _lobes(n, {"view": view, "n1": n1}, {"cos": cos1, "eta": ior, "alpha": alpha},
                 dist, ("e_r", "k_r", "e_t", "k_t"), ("axis_r", "p_t"), front=True)
    if out is None:
        return None
    return FrontLobes(e_r=out["e_r"], k_r=out["k_r"], axis_r=out["axis_r"],
                      e_t1=out["e_t"], k_t1=out["k_t"], p_t1=out["p_t"])


def exit_lobes(cos: torch.Tensor, eta: torch.Tensor, alpha: torch.Tensor, dist: torch.Tensor,
               var: torch.Tensor | None = None):
    """An exit's transmitted lobe sharpness (``lobes.sg_lobe(..., "transmit")[1]``) and,
    with ``var``, ``lobes.spread_energies`` (e_t, e_r) of N points in one kernel call (the
    fused kernels' own lookups): ``(k_t, e_t, e_r)`` (the energies None without ``var``);
    ``None`` where it does not run (as :func:`incident_sg`)."""
    n = cos.shape[0]
    scal = {"cos": cos, "eta": eta, "alpha": alpha}
    if var is not None:
        scal["var"] = var
    outs = ("k_t", "e_t", "e_r") if var is not None else ("k_t",)
    out = _lobes(n, {}, scal, dist, outs, (), front=False)
    if out is None:
        return None
    return out["k_t"], out.get("e_t"), out.get("e_r")


def _lobes(n: int, vec3: dict, scal: dict, dist: torch.Tensor, outs: tuple, outs3: tuple,
           front: bool) -> dict | None:
    """Run csrc/rousiers.c's ``lobes`` on n points: ``vec3`` (N, 3) and ``scal`` (N,)
    float32 inputs, ``dist`` (N,) int64; the named outputs (N,) and ``outs3`` (N, 3)."""
    ins = (*vec3.values(), *scal.values())
    if (not (settings.current().fused and native.available()) or dist.shape != (n,)
            or any(x.shape != (n, 3) for x in vec3.values())
            or any(x.shape != (n,) for x in scal.values())
            or not native.no_grad_through(*ins)):
        return None
    kept = native._inputs(ins, (dist,))
    if kept is None:
        return None
    held = dict(zip((*vec3, *scal, "dist"), kept))
    res = {k: torch.empty(n) for k in outs} | {k: torch.empty(n, 3) for k in outs3}
    if n == 0:
        return res
    keep = _Keep()
    job = native._LobesJob(table=_table(keep), n=n, front=int(front),
                           **{k: v.data_ptr() for k, v in held.items()},
                           **{k: v.data_ptr() for k, v in res.items()})
    return res if native._call("lobes", job) else None


def _lighting_tensors(lighting) -> tuple:
    """The tensors of a batch's lighting a gradient may want."""
    return (lighting.rotate_deg, lighting.scale, lighting.light_pos, lighting.light_radius,
            lighting.light_radiance, *lighting.texels)


def specular(g, lighting, materials, options, radiance: torch.Tensor
             ) -> tuple[torch.Tensor, dict] | None:
    """``render_specular``'s radiance (B, H, W, 3) and passes (``exit_found``, ``tir``; with
    internal bounces ``bounces``, ``bounce_residual``), shaded over ``radiance`` (B*H*W, 3),
    the background (written in place); ``None``, and ``radiance`` untouched, where the fused
    kernel does not run (module docstring)."""
    return _paths(g, lighting, materials, options, radiance, blur=False)


def prefiltered(g, lighting, materials, options, radiance: torch.Tensor
                ) -> tuple[torch.Tensor, dict] | None:
    """``render_prefiltered``'s radiance and passes (``blur_sigma`` too), as
    :func:`specular`."""
    if options.bounces.enabled or lighting.light_pos.shape[1] > 64:
        return None
    return _paths(g, lighting, materials, options, radiance, blur=True)


def rousiers(g, lighting, materials, options, radiance: torch.Tensor, diffuse_var: float,
             coverage: tuple | None = None) -> tuple[torch.Tensor, dict] | None:
    """``render_rousiers``' radiance and passes, as :func:`specular`, internal bounces and
    roughness maps included (``diffuse_var``: rousiers.options.DIFFUSE_VAR; ``coverage``:
    rousiers.cone.coverage_mips where the batch has a map)."""
    if lighting.light_pos.shape[1] > 64 or options.spread != "rays":
        return None
    made = _frame(g, lighting, materials, options, radiance, sg_env=True)
    if made is None:
        return None
    frame, keep, radiance, passes = made
    b, h, w = g.shape
    job = rous_job(g, options, frame, keep, passes, diffuse_var)
    if coverage is not None:  # one exit lobe per roughness level (sec. 5.1)
        levels, mips = coverage
        job.levels, job.mips = levels.shape[1], len(mips)
        job.level_alpha = keep.ptr(levels.clamp(min=mf.ALPHA_MIN))
        job.cover = keep.array(mips)
        job.cover_hw = keep.ptr(torch.tensor([m.shape[1:3] for m in mips]), torch.int64)
    if frame.n and not _run("rousiers", job, g, radiance, passes):
        return None
    return radiance.view(b, h, w, 3), passes


def rous_job(g, options, frame, keep: _Keep, passes: dict, diffuse_var: float
             ) -> native._RousJob:
    """The ``RousJob`` of csrc/rousiers_core.h's cone methods (``rousiers``, and inside
    csrc/lean.c's job ``lean``/``gsr``) over ``frame``: the cone's march, the bounces, and
    the passes ``lobe_sigma``, ``footprint`` it writes (added to ``passes``)."""
    b, h, w = g.shape
    sigma, foot = torch.zeros(b * h * w), torch.zeros(b * h * w)
    passes.update(lobe_sigma=sigma.view(b, h, w, 1), footprint=foot.view(b, h, w, 1))
    plane = options.cone_rays == "plane"
    return native._RousJob(
        f=frame, cone_steps=options.cone_march_steps, cone_refine=options.cone_refine_steps,
        two_ln4=2.0 * math.log(4.0), lobe_sigma=sigma.data_ptr(), footprint=foot.data_ptr(),
        bo=_bounces(g, options.bounces, frame, keep, passes), diffuse_var=diffuse_var,
        plane=int(plane), h=h, w=w,
        back_normal=keep.ptr(g.back.normal) if plane else None,
        back_mask=keep.ptr(g.back.mask, torch.uint8) if plane else None)


def _bounces(g, bs, frame, keep: _Keep, passes: dict) -> native._Bounces:
    """csrc/bounces.h's budget for ``bs`` (bounces.BounceSettings), with the slab planes of
    the inside march and the bounce passes (added to ``passes``) where it is not 0."""
    if not bs.enabled:
        return native._Bounces(limit=0)
    b, h, w = g.shape
    counts, resid = torch.zeros(b * h * w), torch.zeros(b * h * w)
    passes.update(bounces=counts.view(b, h, w, 1), bounce_residual=resid.view(b, h, w, 1))
    return native._Bounces(
        limit=bs.limit, rays=bs.bounce_rays, steps=bs.bounce_march_steps, tol=bs.tolerance,
        bounces=counts.data_ptr(), residual=resid.data_ptr())


def _paths(g, lighting, materials, options, radiance: torch.Tensor, blur: bool
           ) -> tuple[torch.Tensor, dict] | None:
    """csrc/specular.c over the object pixels: ``specular``, or ``prefiltered`` (``blur``)."""
    made = _frame(g, lighting, materials, options, radiance, sg_env=blur)
    if made is None:
        return None
    frame, keep, radiance, passes = made
    b, h, w = g.shape
    sigma = torch.zeros(b * h * w if blur else 1)  # (read by the kernel with ``blur`` only)
    if blur:
        passes["blur_sigma"] = sigma.view(b, h, w, 1)
    job = native._SpecJob(f=frame, blur=int(blur), blur_sigma=sigma.data_ptr(),
                          bo=_bounces(g, options.bounces, frame, keep, passes))
    if frame.n and not _run("specular", job, g, radiance, passes):
        return None
    return radiance.view(b, h, w, 3), passes


def _run(name: str, job, g=None, radiance: torch.Tensor | None = None,
         passes: dict | None = None, lib=None) -> bool:
    """Run fused kernel ``name`` (of ``lib``, a ctypes library built with this package's
    frame.h; None: these kernels) on ``job``, timed as the stage ``fused``. Where ``g``
    carries the later levels of adaptive shading (``g.lattice``), the kernel's pixels are
    the first pass and csrc/lattice.c then fills and shades every level in place on
    ``radiance`` (B*H*W, 3) and ``passes`` (adaptive.fill and adaptive.merge, the same
    values), so the level statuses are left with no waiting pixel."""
    with stage("fused"):
        if g is None or g.lattice is None:
            return native._call(name, job) if lib is None else native._call(name, job, lib)
        return _run_lattice(name, job, g, radiance, passes, lib)


def _run_lattice(name: str, job, g, radiance: torch.Tensor, passes: dict, lib=None) -> bool:
    """csrc/lattice.c's ``lattice_shade`` around kernel ``name`` (:func:`_run`)."""
    frame = job
    while not isinstance(frame, native._Frame):  # the job's Frame: its first field, nested
        frame = getattr(frame, frame._fields_[0][0])
    assert ctypes.addressof(frame) == ctypes.addressof(job)
    levels = g.lattice.levels
    return _settled(_drive(native.entry(name, lib), ctypes.addressof(job), levels, g.shape,
                           radiance, passes), levels, name)


def _settled(ran: bool | None, levels, name: str) -> bool:
    """Whether :func:`_drive` ran (``None``: it did not start: ``False``); a failure after
    a level changed the image raises (the caller cannot fall back to its tensor code)."""
    if ran is None or ran:
        return bool(ran)
    if not all(adaptive.waiting(lv) for lv in levels):  # failed after a level
        raise MemoryError(f"adaptive shading ({name}): no memory for a level's pass")
    return False  # the first pass failed: nothing written, the tensor code runs


_PASS_FN = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_int)
"""csrc/lattice.c's ``tr_kernel_fn``: a level's pass, ``(job, threads) -> 0`` (ok) or -1."""


def lattice_levels(levels, shape: tuple[int, int, int], radiance: torch.Tensor,
                   passes: dict, shade) -> bool:
    """adaptive.fill and adaptive.merge of every level of a lattice after a first pass
    run by a method's tensor code, in csrc/lattice.c's driver (the fused methods' own
    loop; the same values) with ``shade(idx)`` as each level's pass: it shades the frame's
    pixels ``idx`` ((N,) int64, frame order) over ``radiance`` (B, H, W, 3) and writes
    their radiance and ``passes`` (B, H, W, C each) there, in place. ``False`` where the
    driver does not run (nothing changed: the caller loops in Python); an exception of
    ``shade`` is raised here."""
    if not native.available():
        return False
    failed: list[BaseException] = []

    @_PASS_FN
    def run(job: int, threads: int) -> int:
        try:
            f = native._Frame.from_address(job)
            if f.n > 0:  # (the driver calls with pixels left only)
                shade(torch.frombuffer((ctypes.c_int64 * f.n).from_address(f.idx),
                                       dtype=torch.int64).clone())
            return 0
        except BaseException as exc:  # noqa: BLE001 (raised below, after the driver)
            failed.append(exc)
            return -1

    frame = native._Frame(n=0)  # no first pass: the tensor code's is done
    ran = _drive(ctypes.cast(run, ctypes.c_void_p).value, ctypes.addressof(frame), levels,
                 shape, radiance, passes)
    if failed:
        raise failed[0]
    return _settled(ran, levels, "a level's pass in Python")


def _drive(run: int, job: int, levels, shape: tuple[int, int, int], radiance: torch.Tensor,
           passes: dict) -> bool | None:
    """csrc/lattice.c's ``lattice_shade``: ``run`` (a ``tr_kernel_fn``'s address) on
    ``job`` (a ``Frame`` first) for the first pass and each level's; ``None`` where the
    buffers do not suit it (nothing run), else whether it returned 0. The kernel writes
    the level statuses, radiance and passes in place: no copies."""
    b, h, w = shape
    if not all(x.is_contiguous() for lv in levels for x in (lv.status, lv.gap)):
        return None
    if not (radiance.is_contiguous() and radiance.dtype == torch.float32
            and radiance.device.type == "cpu"):
        return None
    if not all(v.is_contiguous() and v.dtype == torch.float32 and v.device.type == "cpu"
               for v in passes.values()):
        return None
    rows = (native._ShadeLevel * len(levels))(*[native._ShadeLevel(
        stride=lv.frame_stride, h=lv.status.shape[1], w=lv.status.shape[2],
        status=lv.status.data_ptr(), gap=lv.gap.data_ptr(),
        rtol=adaptive.fill_rtol(lv)) for lv in levels])
    bufs = list(passes.values())  # (B, H, W, C) each, contiguous: (B*H*W, C)
    ptrs = (ctypes.c_void_p * max(1, len(bufs)))(*[x.data_ptr() for x in bufs])
    chans = torch.tensor([x.numel() // (b * h * w) for x in bufs] or [0], dtype=torch.int64)
    drv = native._LatticeShadeJob(
        run=run, job=job, b=b, h=h, w=w,
        nlevels=len(levels), levels=ctypes.cast(rows, ctypes.c_void_p),
        blend_from=adaptive.BLEND_FROM, radiance=radiance.data_ptr(), npass=len(bufs),
        pass_ptr=ctypes.cast(ptrs, ctypes.c_void_p), pass_ch=chans.data_ptr())
    return native._call("lattice_shade", drv)


def _frame(g, lighting, materials, options, radiance: torch.Tensor, sg_env: bool,
           march: bool = True):
    """The ``Frame`` of csrc/frame.h for a batch, shading over ``radiance`` (B*H*W, 3, the
    background), the tensors it points into, the radiance and the passes every method
    writes; ``None`` where no fused kernel runs for it. ``march`` False: without the
    march's fields and the passes it writes, ``exit_found`` and ``tir`` (a kernel that
    marches nothing: ``sh``'s)."""
    if (options.tir not in TIR_RULES or radiance.dtype != torch.float32
            or not radiance.is_contiguous() or not _runs(g, lighting, materials)):
        return None
    b, h, w = g.shape
    exit_found = tir = None
    passes = {}
    if march:
        exit_found, tir = torch.zeros(b * h * w), torch.zeros(b * h * w)
        passes = {"exit_found": exit_found.view(b, h, w, 1), "tir": tir.view(b, h, w, 1)}
    idx = g.object_index()
    keep = _Keep()
    if idx.numel() == 0:
        return native._Frame(n=0), keep, radiance, passes
    ptr = keep.ptr
    bi = g.object_views()
    # paths.trace_paths' switch: the rough energies for all where any entry point is rough
    # (without roughness maps a view's entry points have its roughness: no gather)
    maps = list(materials.roughness_maps) or [None] * b
    if materials.has_maps:
        rough = bool((materials.roughness_at(
            bi, g.front.uv.reshape(-1, 2).index_select(0, idx)) > 0).any())
    else:
        rough_views = [a > 0 for a in materials.roughness.tolist()]
        rough = any(rough_views)
        if rough and not all(rough_views):  # the views holding a shaded pixel decide:
            # idx is sorted, so where it crosses view ends
            ends = torch.searchsorted(idx, torch.arange(1, b + 1, dtype=idx.dtype) * (h * w))
            shaded = torch.diff(ends, prepend=ends.new_zeros(1)) > 0
            rough = bool((shaded & (materials.roughness > 0)).any())
    dist = torch.tensor([_DIST[d] for d in materials.distribution], dtype=torch.int64)
    # the escape fraction: ``conserve``'s, and with internal bounces a lost ray's
    esc = escape_grid(load_sg_table(), materials.ior, dist, torch.float32) \
        if options.tir == "conserve" or options.bounces.enabled else torch.ones(b, 2)
    march = _march_job(g, options, keep) if march else native._Job()
    if march is None:
        return None
    frame = native._Frame(
        n=idx.numel(), nb=b, idx=ptr(idx, torch.int64), batch=ptr(bi, torch.int64),
        ray_dir=ptr(g.ray_dir), front_pos=ptr(g.front.position),
        front_normal=ptr(g.front.normal), front_dist=ptr(g.front.dist),
        back_dist=ptr(g.back.dist), eye=ptr(g.eye), basis=ptr(g.proj[:, 3:12]),
        proj=ptr(g.proj), sphere_c=ptr(g.meshes.sphere_center),
        sphere_r=ptr(g.meshes.sphere_radius), march=march, ior=ptr(materials.ior),
        alpha=ptr(materials.roughness), absorption=ptr(materials.absorption),
        dist=ptr(dist, torch.int64), tir_mode=TIR_RULES.index(options.tir),
        rough=int(rough), rmap=keep.array(maps),
        rmap_hw=ptr(torch.tensor([(1, 1) if m is None else m.shape for m in maps]),
                    torch.int64),
        rrange=ptr(materials.roughness_range if materials.roughness_range is not None
                   else torch.zeros(b, 2)),
        front_uv=ptr(g.front.uv), tri_uvs=ptr(g.meshes.tri_uvs),
        table=_table(keep), esc=ptr(esc), esc_n=esc.shape[1],
        lights=_lights(lighting, keep), env=_sg_env(lighting, keep) if sg_env else
        native._SgEnv(), radiance=radiance.data_ptr(),
        exit_found=None if exit_found is None else exit_found.data_ptr(),
        tir=None if tir is None else tir.data_ptr())
    return frame, keep, radiance, passes


def _march_job(g, options, keep: _Keep) -> native._Job | None:
    """The ``Job`` of csrc/march_core.h a frame's marches share: the marched layers (the
    front's too where bounces march between them), the frame's where g is a strip of it;
    the bounces' march sets pw 8 itself. ``None`` where the layers do not suit it."""
    mf = native.march_fields(camera_planes(g, both=options.bounces.enabled),
                             options.bounces.enabled)
    if mf is None:
        return None
    keep.extend(mf.pop("keep"))
    mf["pw"] = 4
    mh, mw = mf["h"], mf["w"]
    ptr = keep.ptr
    return native._Job(
        steps=options.march_steps, refine=options.refine_steps,
        sx_v=ptr(0.5 * mw / g.proj[:, 12]), sy_v=ptr(0.5 * mh / g.proj[:, 13]),
        tv=ptr(g.meshes.tri_vertices), across=ptr(g.meshes.tri_across, torch.int64),
        walk_steps=16, tn=ptr(g.meshes.tri_normals), **mf)


__all__ = ["background", "exit_lobes", "front_lobes", "incident_sg", "lattice_levels",
           "prefiltered", "rousiers", "specular"]
