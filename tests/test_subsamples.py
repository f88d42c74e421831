"""Sparse supersampling (torchrefract.geometry.subsamples, torchrefract.sparse): with n x n
samples per pixel, the one-sample render with the pixels whose samples can differ replaced
by their samples' box filter, shaded from a G-buffer of those samples alone."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
from conftest import SH_SMALL

import torchrefract as tr
from torchrefract import sparse, tiles
from torchrefract.geometry import subsamples
from torchrefract.geometry.camera import subpixel_rays, views_pixel_rays
from torchrefract.geometry.gbuffer import build_gbuffer, build_sparse
from torchrefract.geometry.mesh import load_mesh
from torchrefract.geometry.raster import visibility_layers
from torchrefract.kernels import native
from torchrefract.lighting.lights import Lighting
from torchrefract.methods.rousiers import cone as cone_module, shade as rousiers_shade
from torchrefract.methods.rousiers.cone import level_coverage
from torchrefract.optics.ndf import build_box_mips
from torchrefract.methods import registry
from torchrefract.optics.materials import MaterialBatch
from torchrefract.result import front_roughness
from torchrefract.settings import RenderSettings, using
from torchrefract.truth.metrics import flip_map

SUITE = Path(__file__).resolve().parent.parent / "configs" / "suite"
UNIFORM = RenderSettings(adaptive=False)


def _scene(name: str, size: int = 48, n: int = 2, **changes) -> tr.Scene:
    s = tr.load_scene(SUITE / f"{name}.yaml")
    return s.replace(camera=dataclasses.replace(s.camera, width=size, height=size,
                                                samples_per_pixel=n), **changes)


def _one_sample(scenes: list[tr.Scene], with_flags: bool = False):
    """The one-sample G-buffer (marching the n x n ids), the n x n ids and the front
    roughness of ``scenes`` (``with_flags``: and the rasterizer's sub-pixel flags)."""
    g, ids, flags = sparse.gbuffer([load_mesh(s.mesh, s.transform) for s in scenes],
                                   [s.camera for s in scenes])
    g = dataclasses.replace(g, marched=subsamples.marched(g, ids))
    alpha = front_roughness(g, MaterialBatch.from_scenes(scenes))
    return (g, ids, alpha, flags) if with_flags else (g, ids, alpha)


def test_subpixel_rays_are_the_pixel_rays():
    cams = [tr.Camera(width=7, height=5, samples_per_pixel=3),
            tr.Camera(width=7, height=5, eye=(1.0, 2.0, 3.0), yfov_deg=20.0)]
    full = views_pixel_rays(cams, 3)
    gen = torch.Generator().manual_seed(0)
    rows, cols = torch.randint(0, 15, (2, 40), generator=gen), torch.randint(0, 21, (2, 40),
                                                                             generator=gen)
    want = torch.stack([full[b][rows[b], cols[b]] for b in range(2)])
    assert torch.equal(subpixel_rays(cams, 3, rows, cols), want)  # the kernel's
    with using(RenderSettings(native=False)):  # the tensor code's
        assert torch.equal(subpixel_rays(cams, 3, rows, cols), want)


def test_sparse_gbuffer_is_the_one_sample_one():
    """build_sparse: the one-sample G-buffer, bit for bit, and the n x n ids (views
    repeated in the batch drawn once)."""
    s = _scene("wingnut_a01", 40)
    other = s.replace(camera=dataclasses.replace(s.camera, eye=(0.3, 0.4, 3.5)))
    meshes = [load_mesh(s.mesh, s.transform)] * 3
    cams = [s.camera, other.camera, s.camera]
    g, ids, flags = build_sparse(meshes, cams)
    assert flags is None  # (no fold tolerances given)
    one = build_gbuffer(meshes, [dataclasses.replace(c, samples_per_pixel=1) for c in cams])
    for lay in ("front", "back"):
        for f in ("mask", "tri", "dist", "normal"):
            assert torch.equal(getattr(getattr(g, lay), f), getattr(getattr(one, lay), f))
    full = build_gbuffer(meshes, cams)
    assert g.supersample == 1 and ids[0].shape == full.front.tri.shape
    covered = full.front.mask  # the ids there, but where the edge repair changed one
    assert float((ids[0][covered] != full.front.tri[covered]).float().mean()) < 0.01
    assert torch.equal(ids[0][2], ids[0][0])


def test_int32_ids_are_the_int64_ones():
    s = _scene("wingnut_a01", 40)
    m = [load_mesh(s.mesh, s.transform)]
    a = visibility_layers(m, [s.camera], 2, [5])
    b = visibility_layers(m, [s.camera], 2, [5], dtype=torch.int32)
    assert b[0].dtype == torch.int32 and (a[0] >= 0).any()
    assert all(torch.equal(x, y.long()) for x, y in zip(a, b))


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
@pytest.mark.parametrize("name", ["bunny_a01", "globe_gradient", "vgroove_back_a01",
                                  "sphere_a0"])
def test_edges_kernel_makes_the_tensor_codes_decisions(name):
    """csrc/lattice.c's ``edges`` against the tensor code, per-view roughness and a map's
    (globe_gradient), at 2x2 and 3x3, over two views."""
    for n in (2, 3):
        s = _scene(name, 40, n)
        views = [s, s.replace(camera=dataclasses.replace(s.camera, eye=(0.3, 0.4, 3.5)))]
        g, ids, alpha, flags = _one_sample(views, with_flags=True)
        assert flags is not None
        want = subsamples._edges_torch(g, ids, alpha, subsamples.NORMAL_TOL,
                                       subsamples.DEPTH_TOL, 0.02, subsamples.FACE_TOL)
        assert want.any() and not want.all(), (name, n)
        # the rasterizer's flags, and flags made from the ids
        assert torch.equal(subsamples.edges(g, ids, alpha, flags=flags), want), (name, n)
        assert torch.equal(subsamples.edges(g, ids, alpha), want), (name, n)


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
@pytest.mark.parametrize("n", [2, 3])
def test_rasterizer_flags_are_those_of_its_ids(n):
    """csrc/raster.c's sub-pixel flags, made as it writes the ids (one view: its rows drawn
    in bands by two threads; three: a repeated view copied), equal the flags made from
    the ids afterwards; a crease (the v-groove) and silhouettes set the differing bits."""
    s = _scene("vgroove_back_a01", 40, n)
    other = s.replace(camera=dataclasses.replace(s.camera, eye=(0.3, 0.4, 3.5)))
    threads = torch.get_num_threads()
    for views in ([s], [s, other, s]):
        torch.set_num_threads(2)
        try:
            g, ids, _, flags = _one_sample(views, with_flags=True)
        finally:
            torch.set_num_threads(threads)
        want = native.sub_flags(ids, native.SubTest(n, g.meshes, *subsamples.FOLDS))
        assert flags.shape == g.shape and torch.equal(flags, want), (n, len(views))
        for bit in (1, 2, 4, 8):  # each bit set somewhere, and clear somewhere
            assert (flags & bit).any() and not (flags & bit).all(), (n, bit)


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
@pytest.mark.parametrize("n,w,h", [(2, 37, 29), (2, 13, 11), (3, 37, 29)])
def test_edges_at_an_odd_size_are_the_tensor_codes(n, w, h):
    """Frames whose rows end in pixels past the kernels' groups of eight (at 13 pixels
    wide, the object among them): the rasterizer's flags and ``edges`` make the tensor
    code's decisions."""
    s = _scene("wingnut_a01", w, n)
    s = s.replace(camera=dataclasses.replace(s.camera, height=h))
    g, ids, alpha, flags = _one_sample([s], with_flags=True)
    want = subsamples._edges_torch(g, ids, alpha, subsamples.NORMAL_TOL, subsamples.DEPTH_TOL,
                                   0.02, subsamples.FACE_TOL)
    assert want.any() and not want.all()
    assert torch.equal(subsamples.edges(g, ids, alpha, flags=flags), want)


def test_every_pixel_of_partial_coverage_is_picked():
    """The n x n render's coverage is fractional exactly where a silhouette crosses a
    pixel's samples: each such pixel is picked."""
    s = _scene("slab_a02", 48)
    g, ids, alpha = _one_sample([s])
    picked = subsamples.edges(g, ids, alpha)
    cov = tr.render(s, settings=UNIFORM).coverage
    partial = (cov > 0) & (cov < 1)
    assert partial.any() and bool(picked[partial].all())
    assert float(picked[g.front.mask].float().mean()) < 0.5  # the interior mostly not


@pytest.mark.parametrize("name", ["bunny_a01", "vgroove_back_a01", "sphere_a03"])
def test_samples_are_the_supersampled_gbuffer(name):
    """Every pixel picked: the samples' layers are the n x n G-buffer's and the ids they
    march through its layers' ids, bit for bit but where a sample's ray meets a shared
    edge (the edge repair takes the first of equal hits, its candidates in another order:
    the same point, the other triangle)."""
    s = _scene(name, 40)
    g, ids, _ = _one_sample([s])
    full = build_gbuffer([load_mesh(s.mesh, s.transform)], [s.camera])
    got = subsamples.gather(g, ids, [s.camera], torch.ones(1, 40, 40, dtype=torch.bool))
    p = got.pixels[0]
    assert torch.equal(p, torch.arange(1600))
    ties = 0
    for lay, want in ((got.g.front, full.front), (got.g.back, full.back)):
        for f in ("mask", "tri", "dist", "depth", "normal", "uv"):
            x = getattr(lay, f).view(1, 40, 40, 2, 2, -1).permute(0, 1, 3, 2, 4, 5)
            x, y = x.reshape(getattr(want, f).shape), getattr(want, f)
            if f == "tri":
                ties += int((x != y).sum())
            else:
                assert torch.allclose(x.float(), y.float(), rtol=0, atol=1e-5), f
                assert f != "mask" or torch.equal(x, y)
    assert ties <= 4, ties
    marched = [got.g.marched.back, got.g.marched.front]
    tri = [full.back.tri.reshape(-1), full.front.tri.reshape(-1)]
    assert sum(int((a != b).sum()) for a, b in zip(marched, tri)) == ties


def test_samples_read_the_roughness_coverage_of_the_one_sample_frame():
    """With a roughness map, ``rousiers`` reads the roughness levels' coverage over the
    frame its footprints are measured in: for scattered samples, as for the first pass,
    the one-sample frame's back layer (``Marched.back_uv``), not the samples' own."""
    s = _scene("globe_jump", 24)
    g, ids, _ = _one_sample([s])
    mat = MaterialBatch.from_scenes([s])
    picked = torch.zeros(1, 24, 24, dtype=torch.bool)
    picked[0, 6:18, 8:16] = True
    got = subsamples.gather(g, ids, [s.camera], picked)
    frame = level_coverage(g, mat, 4)
    assert frame.shape == (1, 24, 24, 4) and float(frame.sum()) > 0
    assert torch.equal(level_coverage(got.g, mat, 4), frame)


def test_coverage_mips_are_made_once_for_both_passes(monkeypatch):
    """A sparse render with a roughness map makes the coverage mips once (the one-sample
    frame's) and its samples' pass reads them again: the same image as made twice."""
    s = _scene("globe_jump", 32, method="rousiers")
    made = []
    real = cone_module.level_coverage

    def counted(*a, **k):
        made.append(1)
        return real(*a, **k)

    once = tr.render(s)
    monkeypatch.setattr(cone_module, "level_coverage", counted)
    assert torch.equal(tr.render(s).radiance, once.radiance) and len(made) == 1
    monkeypatch.setattr(rousiers_shade, "coverage_mips", lambda g, m, n: (
        cone_module.level_values(m, n), build_box_mips(real(g, m, n))))  # made per pass
    assert torch.equal(tr.render(s).radiance, once.radiance)


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
def test_slots_kernel_lays_out_the_samples_as_the_tensor_code():
    """csrc/index.c's ``sample_slots`` and ``put_ids`` against the tensor code: random picks
    over three views (one with none, one with all), 2x2 and 3x3 samples, odd sizes."""
    g = torch.Generator().manual_seed(3)
    for n, (h, w) in ((2, (7, 9)), (3, (5, 6)), (2, (16, 33))):
        picked = torch.rand(3, h, w, generator=g) > 0.6
        picked[1] = False
        picked[2] = True
        ids = tuple(torch.randint(-1, 50, (3, n * h, n * w), generator=g, dtype=torch.int32)
                    for _ in range(2))
        got, want = subsamples._slots(picked, ids, n), subsamples._slots_torch(picked, ids, n)
        for a, b in zip(got, want):
            for x, y in (zip(a, b) if isinstance(a, tuple) else ((a, b),)):
                assert x.dtype == y.dtype and torch.equal(x, y), n
        pixels, _, _, _, flat, taken = got
        tri = tuple(torch.randint(0, 99, (3, pixels.shape[1] * n * n), generator=g,
                                  dtype=torch.int32) for _ in range(2))
        put, ref = tuple(x.clone() for x in ids), tuple(x.clone() for x in ids)
        assert native.put_ids(put, flat, taken, tri)
        for x, t in zip(ref, tri):
            x.view(-1).index_copy_(0, flat, t.view(-1).index_select(0, taken))
        assert all(torch.equal(a, b) for a, b in zip(put, ref))
    none = torch.zeros(2, 4, 4, dtype=torch.bool)
    ids = tuple(torch.zeros(2, 8, 8, dtype=torch.int32) for _ in range(2))
    assert subsamples._slots(none, ids, 2) is None and subsamples._slots_torch(none, ids, 2) \
        is None


def test_no_pixel_picked_gives_no_samples():
    s = _scene("slab_a02", 16)
    g, ids, _ = _one_sample([s])
    assert subsamples.gather(g, ids, [s.camera], torch.zeros(1, 16, 16, dtype=torch.bool)) \
        is None


def _options(method: str) -> dict:
    """A method's options for the tests below: internal bounces, or a small ``sh`` table."""
    return dict(SH_SMALL) if method == "sh" else {"internal_bounces": 2}


@pytest.mark.parametrize("method", ["rousiers", "specular", "sh", "lean"])
def test_smooth_glass_is_the_uniform_render_on_the_object(method):
    """Below SMOOTH_ALPHA every object pixel is picked: there the image is the uniform
    n x n render's, bit for bit; at 32 pixels a pixel spans several texels of the map, so
    every background pixel averages its samples too: the whole image is the uniform one."""
    s = _scene("sphere_a0", 32, method=method, method_options=_options(method))
    a, b = tr.render(s, settings=UNIFORM), tr.render(s)
    assert torch.equal(a.coverage, b.coverage)
    assert torch.equal(a.radiance, b.radiance)


def test_background_pixels_are_supersampled_where_the_environment_needs_it():
    """A background pixel averages its n x n samples where the map has detail finer than
    a pixel (``sparse.fine_environment``, per view) or its neighbours' radiances spread
    (a sphere light's edge); elsewhere its center sample is the samples' bilinear mean.
    Either way it is the uniform render's up to the map's bilinear curvature."""
    light = (tr.SphereLight(position=(0.9, 0.5, 0.0), radius=0.15, radiance=(20.0,) * 3),)
    coarse = _scene("sphere_a03", 128, method="rousiers", lights=light)
    fine = _scene("sphere_a03", 24, method="rousiers")
    lighting = Lighting.from_scenes([coarse, fine])
    assert sparse.fine_environment([coarse, fine], lighting) == [False, True]
    for s in (coarse, fine):
        a, b = tr.render(s, settings=UNIFORM), tr.render(s)
        bg = a.coverage[0] == 0
        d = (a.radiance[0] - b.radiance[0]).abs().amax(-1)[bg]
        assert float(d.max()) < 0.05, s.camera.width  # (9.9 at the light's edge without)
        assert float(d.mean()) < 1e-3


def test_a_view_renders_as_alone_whatever_its_batch():
    """A batch whose views would not all take sparse supersampling alone (``lean`` beside
    a roughness map) renders each group as its views render alone."""
    plain = _scene("sphere_a03", 24, method="lean")
    mapped = _scene("globe_jump", 24, method="lean")
    assert mapped.material.roughness_map is not None
    alone = tr.render([plain]).radiance[0]
    both = tr.render([plain, mapped, plain]).radiance
    assert torch.equal(both[0], alone) and torch.equal(both[2], alone)
    assert torch.equal(both[1], tr.render([mapped]).radiance[0])


@pytest.mark.parametrize("name,method", [("bunny_a01", "rousiers"),
                                         ("vgroove_back_a01", "rousiers"),
                                         ("slab_light", "rousiers"), ("teapot_a01", "sh"),
                                         ("wingnut_a01", "lean")])
def test_sparse_render_is_close_to_the_uniform_one(name, method):
    """The default 2x2 render: the uniform one's coverage exactly, its image closer to the
    uniform one's than the one-sample image is, every pass present and finite."""
    opts = SH_SMALL if method == "sh" else {}
    s = _scene(name, 64, method=method, method_options=opts)
    a, b = tr.render(s, settings=UNIFORM), tr.render(s)
    one = tr.render(_scene(name, 64, 1, method=method, method_options=opts))
    assert torch.equal(a.coverage, b.coverage)
    obj = (a.coverage[0] > 0).numpy()
    near = float(flip_map(a.radiance[0].numpy(), b.radiance[0].numpy())[obj].mean())
    assert near < 0.05 and near < 0.6 * float(
        flip_map(a.radiance[0].numpy(), one.radiance[0].numpy())[obj].mean())
    assert set(a.passes) == set(b.passes)
    assert all(bool(torch.isfinite(v).all()) for v in b.passes.values())


@pytest.mark.skipif(not native.available(), reason="the native kernels do not build here")
@pytest.mark.parametrize("name,method,options", [
    ("bunny_a01", "rousiers", {}), ("slab_light", "sh", SH_SMALL),
    ("globe_jump", "rousiers", {}), ("teapot_a01", "lean", {})])
def test_sparse_fused_matches_the_tensor_code(name, method, options):
    """The samples' G-buffer shaded by the fused kernel and by the tensor code: as
    tests/test_fused.py holds them on full frames."""
    s = _scene(name, 48, method=method, method_options=options)
    a = tr.render(s, settings=RenderSettings(fused=False))
    b = tr.render(s, settings=RenderSettings(fused=True))
    obj = a.coverage[0] > 0
    rel = ((a.radiance - b.radiance).abs() / a.radiance.abs().clamp(min=1e-3)).amax(-1)[0]
    assert float((rel[obj] > 1e-4).float().mean()) <= 1e-3
    flip = flip_map(b.radiance[0].numpy(), a.radiance[0].numpy())
    assert float(flip[obj.numpy()].mean()) <= 0.002


def test_which_passes_are_sparse():
    """Methods that shade their samples alone, at n x n, adaptive, on the CPU; the others
    and the n x n plan keep the full sub-pixel G-buffer."""
    entry = registry.get("rousiers")
    opts = entry.parse({})
    s = _scene("slab_a02", 16, method="rousiers")
    mat = MaterialBatch.from_scenes([s])
    assert sparse.applies([s], entry, opts, mat)
    assert not sparse.applies([_scene("slab_a02", 16, 1)], entry, opts, mat)
    plane = entry.parse({"cone_rays": "plane"})
    assert not sparse.applies([s], entry, plane, mat)
    globe = _scene("globe_jump", 16, method="rousiers")  # a roughness map: read through
    assert sparse.applies([globe], entry, opts, MaterialBatch.from_scenes([globe]))  # back_uv
    lean = registry.get("lean")  # without a moments pyramid (moments.reads_no_moments)
    assert sparse.applies([s], lean, lean.parse({}), mat)
    assert not sparse.applies([s], lean, lean.parse({"spread": "paper"}), mat)
    gsr = registry.get("gsr")
    assert not sparse.applies([s], gsr, gsr.parse({}), mat)
    sh = registry.get("sh")  # reads its table at each sample's own front hit
    assert sparse.applies([s], sh, sh.parse({}), mat)


def test_sparse_passes_in_tiles_give_the_untiled_pixels(monkeypatch):
    """Both passes (the one-sample frame's, the samples') cut into tiles of 64 samples:
    the image and every pass are the untiled render's, bit for bit."""
    s = _scene("torus_a01", 64, method="rousiers", method_options={"internal_bounces": 1})
    whole = tr.render(s)
    cuts = []
    real = tiles.split

    def small(idx, size):
        parts = real(idx, 64)
        cuts.append(len(parts))
        return parts

    monkeypatch.setattr(tiles, "tile_size", lambda *a: 64)
    monkeypatch.setattr(tiles, "split", small)
    tiled = tr.render(s)
    assert len(cuts) >= 2 and min(cuts) >= 2, cuts
    assert torch.equal(whole.radiance, tiled.radiance)
    assert torch.equal(whole.coverage, tiled.coverage)
    assert all(torch.equal(whole.passes[k], tiled.passes[k]) for k in whole.passes)


def test_samples_written_over_the_image_keep_gradients():
    """sparse._put: the samples' pixels replace the image's at their pixels (in place
    where no gradient flows), and a gradient flows to the pixels not replaced."""
    rad = torch.zeros(1, 2, 2, 3, requires_grad=True)
    image = tr.RenderResult(radiance=rad * 2.0, coverage=torch.zeros(1, 2, 2),
                            passes={"x": torch.zeros(1, 2, 2, 1)}, scenes=())
    part = tr.RenderResult(radiance=torch.ones(1, 2, 1, 3), coverage=torch.ones(1, 2, 1),
                           passes={"x": torch.ones(1, 2, 1, 1)}, scenes=())
    out = sparse._put(image, part, torch.tensor([[3, -1]]))
    assert out.radiance[0, 1, 1].tolist() == [1.0] * 3 and float(out.coverage[0, 1, 1]) == 1.0
    assert float(out.radiance.detach().sum()) == 3.0 and float(out.passes["x"].sum()) == 1.0
    out.radiance.sum().backward()
    assert rad.grad[0, 0, 0].tolist() == [2.0] * 3 and rad.grad[0, 1, 1].tolist() == [0.0] * 3
    plain = tr.RenderResult(radiance=torch.zeros(1, 2, 2, 3), coverage=torch.zeros(1, 2, 2),
                            passes={}, scenes=())
    assert sparse._put(plain, part, torch.tensor([[0, -1]])).radiance is plain.radiance


def test_samples_written_by_the_kernel_are_the_index_copies():
    """sparse._put's one native call (csrc/box.c ``put_rows``) writes what the tensor
    code's index copies write, in place, for every buffer."""
    gen = torch.Generator().manual_seed(3)

    def image():
        g = torch.Generator().manual_seed(1)
        return tr.RenderResult(radiance=torch.rand(2, 5, 6, 3, generator=g),
                               coverage=torch.rand(2, 5, 6, generator=g),
                               passes={"x": torch.rand(2, 5, 6, 1, generator=g),
                                       "n": torch.rand(2, 5, 6, 3, generator=g)}, scenes=())

    part = tr.RenderResult(radiance=torch.rand(2, 4, 1, 3, generator=gen),
                           coverage=torch.rand(2, 4, 1, generator=gen),
                           passes={"x": torch.rand(2, 4, 1, 1, generator=gen),
                                   "n": torch.rand(2, 4, 1, 3, generator=gen)}, scenes=())
    pixels = torch.tensor([[0, 7, 29, -1], [3, 4, -1, -1]])
    got = image()
    radiance = got.radiance
    out = sparse._put(got, part, pixels)
    assert out.radiance is radiance  # in place
    with using(RenderSettings(native=False)):
        want = sparse._put(image(), part, pixels)
    for a, b in ((out.radiance, want.radiance), (out.coverage, want.coverage),
                 *((out.passes[k], want.passes[k]) for k in ("x", "n"))):
        assert torch.equal(a, b)
    assert torch.equal(out.radiance[1, 0, 4], part.radiance[1, 1, 0])
