"""Image files (OpenEXR, Radiance .hdr) and the environment map: loading, validation, lookup.

Lookup conventions (SCENE_SPEC.md, Mitsuba 3 ``envmap``): u = atan2(x, -z) / 2pi wrapped to
[0, 1), v = acos(y) / pi; column c centered at u = (c + 0.5) / W, row r at v = r / (H - 1);
bilinear, wrapping horizontally; ``rotate_deg`` turns the map about +Y.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchrefract.checks import ConfigError
from torchrefract.lighting.envmap import direction_to_uv, load_envmap, lookup, validate_texels
from torchrefract.output.images import (EXR_COMPRESSIONS, check_exr_compression, read_exr,
                                        read_hdr, write_exr, write_hdr)


def uv_to_dir(u, v):
    """Inverse of the spec's mapping: (u, v) -> unit direction (float64 numpy)."""
    phi, theta = 2.0 * np.pi * np.asarray(u, float), np.pi * np.asarray(v, float)
    return np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)],
                    -1)


def texel_dir(c, r, h, w):
    return uv_to_dir((c + 0.5) / w, r / (h - 1))


# --------------------------------------------------------------------------------------
# OpenEXR
# --------------------------------------------------------------------------------------

def test_exr_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    h, w = 7, 11
    rgb = (rng.random((h, w, 3)) * 10.0 ** rng.uniform(-6, 5, (h, w, 3))).astype(np.float32)
    rgb[0, 0] = [0.0, 65504.0 * 4, 1e-30]  # beyond half range, tiny: float32 kept
    alpha = rng.random((h, w)).astype(np.float32)
    extra = rng.normal(size=(h, w)).astype(np.float32)  # negative values allowed in passes
    path = tmp_path / "sub" / "img.exr"  # folder is created
    write_exr(path, {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": alpha,
                     "depth_front": extra})
    ch = read_exr(path)
    assert set(ch) == {"R", "G", "B", "A", "depth_front"}
    for k, want in (("R", rgb[..., 0]), ("G", rgb[..., 1]), ("B", rgb[..., 2]), ("A", alpha),
                    ("depth_front", extra)):
        assert ch[k].dtype == np.float32 and ch[k].shape == (h, w)
        assert np.array_equal(ch[k], want), k
    # atomic write: no temporary files left beside it
    assert sorted(p.name for p in path.parent.iterdir()) == ["img.exr"]
    # rewriting replaces the file
    write_exr(path, {"R": alpha, "G": alpha, "B": alpha})
    assert set(read_exr(path)) == {"R", "G", "B"}
    assert sorted(p.name for p in path.parent.iterdir()) == ["img.exr"]


@pytest.mark.parametrize("compression", list(EXR_COMPRESSIONS))
def test_every_exr_compression_offered_is_lossless_and_written(tmp_path, compression):
    """Each ``exr_compression`` gives back the float32 bits written, NaN, -0 and denormals
    included, and the file's header names it."""
    import OpenEXR

    rng = np.random.default_rng(1)
    x = (rng.normal(size=(19, 23)) * 10.0 ** rng.uniform(-8, 8, (19, 23))).astype(np.float32)
    x[0, :3] = [np.nan, -0.0, 1e-42]
    chans = {"R": x, "G": x[::-1].copy(), "B": np.zeros_like(x), "depth_front": -x}
    path = tmp_path / f"{compression}.exr"
    write_exr(path, chans, compression)
    back = read_exr(path)
    assert all(back[k].tobytes() == v.tobytes() for k, v in chans.items())
    with OpenEXR.File(str(path)) as f:
        assert str(f.header()["compression"]).endswith(
            EXR_COMPRESSIONS[compression] + "_COMPRESSION")
    with pytest.raises(ConfigError, match=r"exr_compression: 'pxr24' is not one of zip"):
        check_exr_compression("pxr24")  # lossy for float32: not offered


def test_read_exr_rejects_non_exr(tmp_path):
    p = tmp_path / "fake.exr"
    p.write_bytes(b"not an exr file at all")
    with pytest.raises(ConfigError, match="fake.exr"):
        read_exr(p)


def test_load_envmap_exr_rgb_and_luminance(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.random((6, 12, 3)).astype(np.float32) * 5
    p = tmp_path / "env.exr"
    write_exr(p, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
    t = load_envmap(p)
    assert t.dtype == torch.float32 and t.shape == (6, 12, 3)
    assert np.array_equal(t.numpy(), img)
    assert load_envmap(str(p)) is t  # cached per resolved path
    y = rng.random((4, 8)).astype(np.float32)
    py = tmp_path / "lum.exr"
    write_exr(py, {"Y": y})
    assert np.array_equal(load_envmap(py).numpy(), np.repeat(y[..., None], 3, -1))
    pz = tmp_path / "depth_only.exr"
    write_exr(pz, {"Z": y})
    with pytest.raises(ConfigError, match=r"depth_only\.exr.*no R, G, B.*'Z'"):
        load_envmap(pz)


def test_load_envmap_rejects_unknown_format(tmp_path):
    p = tmp_path / "env.png"
    p.write_bytes(b"\x89PNG....")
    with pytest.raises(ConfigError, match=r"env\.png.*unsupported format '\.png'"):
        load_envmap(p)


# --------------------------------------------------------------------------------------
# Radiance .hdr
# --------------------------------------------------------------------------------------

def test_hdr_round_trip_within_rgbe_precision(tmp_path):
    rng = np.random.default_rng(2)
    h, w = 9, 13
    rgb = rng.random((h, w, 3)) * 10.0 ** rng.uniform(-4, 4, (h, w, 1))
    rgb[0, 0] = 0.0
    rgb[0, 1] = [1.0, 0.5, 0.25]  # exact in RGBE
    rgb[0, 2] = [3e4, 1e-3, 0.0]  # very unequal channels
    p = tmp_path / "env.hdr"
    write_hdr(p, rgb)
    back = read_hdr(p)
    assert back.dtype == np.float32 and back.shape == (h, w, 3)
    # RGBE: one shared exponent, 8-bit mantissas; error <= max channel / 128
    err = np.abs(back - rgb).max(-1) / np.maximum(rgb.max(-1), 1e-30)
    assert err.max() <= 1.0 / 128
    assert np.array_equal(back[0, 0], [0, 0, 0])
    assert np.array_equal(back[0, 1], [1.0, 0.5, 0.25])
    # the same through load_envmap
    assert np.array_equal(load_envmap(p).numpy(), back)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["env.hdr"]


def _rle_channel(vals: np.ndarray) -> bytes:
    """New-style RLE of one channel of one scanline: runs (128 + n, value) of 3..127 equal
    bytes and dumps (n, n bytes) of 1..128 others."""
    out, i, n = bytearray(), 0, len(vals)
    while i < n:
        j = i
        while j < n and vals[j] == vals[i] and j - i < 127:
            j += 1
        if j - i >= 3:
            out += bytes([128 + (j - i), int(vals[i])])
            i = j
            continue
        k = i  # literal dump up to the next run of >= 3 (or 128 bytes)
        while k < n and k - i < 128:
            if k + 2 < n and vals[k] == vals[k + 1] == vals[k + 2]:
                break
            k += 1
        out += bytes([k - i]) + bytes(int(x) for x in vals[i:k])
        i = k
    return bytes(out)


def _expected_from_rgbe(rgbe: np.ndarray) -> np.ndarray:
    e = rgbe[..., 3].astype(np.int64)
    f = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)  # 2^(e - 128) / 256 (Radiance/Mitsuba)
    return (rgbe[..., :3] * f[..., None]).astype(np.float32)


def test_hdr_rle_scanlines_are_decoded(tmp_path):
    h, w = 4, 150  # > 128 wide: runs and dumps split across the count limits
    rng = np.random.default_rng(3)
    rgbe = np.zeros((h, w, 4), np.uint8)
    rgbe[..., :3] = rng.integers(128, 256, (h, w, 3))
    rgbe[..., 3] = 130
    rgbe[0, :40] = [200, 100, 50, 129]      # a long run in every channel
    rgbe[1, 10:140, 0] = 255                # a run longer than 127 in one channel
    rgbe[2, ::2, 1] = 7                     # alternating: dumps only
    rgbe[3, 100:] = 0                       # black (exponent 0) run to the end
    header = b"#?RADIANCE\n# made by hand\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1.0\n\n"
    body = bytearray(f"-Y {h} +X {w}\n".encode())
    for y in range(h):
        body += bytes([2, 2, w >> 8, w & 255])
        for c in range(4):
            body += _rle_channel(rgbe[y, :, c])
    assert len(body) < h * w * 4  # it is really compressed
    p = tmp_path / "rle.hdr"
    p.write_bytes(header + bytes(body))
    got = read_hdr(p)
    assert got.shape == (h, w, 3)
    assert np.array_equal(got, _expected_from_rgbe(rgbe))
    assert np.array_equal(got[0, 0], [200 / 128, 100 / 128, 50 / 128])  # 2^(129-136)


def test_hdr_flat_file_by_hand(tmp_path):
    rgbe = np.array([[[128, 64, 32, 128], [0, 0, 0, 0]],
                     [[255, 255, 255, 140], [1, 2, 3, 100]]], np.uint8)
    p = tmp_path / "flat.hdr"
    p.write_bytes(b"#?RGBE\n\n-Y 2 +X 2\n" + rgbe.tobytes())
    got = read_hdr(p)
    assert np.array_equal(got, _expected_from_rgbe(rgbe))
    assert np.array_equal(got[0, 0], [0.5, 0.25, 0.125])


@pytest.mark.parametrize("content,fragment", [
    (b"P6\n2 2\n255\n", "#?"),
    (b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 1 +X 1\n\x80\x80\x80\x80", "xyze"),
    (b"#?RADIANCE\n\n+Y 2 +X 2\n" + bytes(16), "orientation"),
    (b"#?RADIANCE\n\n-Y 2 +X 2\n" + bytes(12), "Radiance"),  # truncated flat data
    (b"#?RADIANCE\n\n-Y 1 +X 8\n\x02\x02\x00\x09" + bytes(40), "bad length"),
    (b"#?RADIANCE\n\n-Y 1 +X 8\n\x02\x02\x00\x08\x88", "Radiance"),  # truncated RLE
])
def test_hdr_rejects_broken_files(tmp_path, content, fragment):
    p = tmp_path / "broken.hdr"
    p.write_bytes(content)
    with pytest.raises(ConfigError) as info:
        read_hdr(p)
    assert "broken.hdr" in str(info.value) and fragment in str(info.value), str(info.value)


def test_hdr_rle_zero_counts_are_an_error(tmp_path):
    # Radiance rejects a count byte of 0 ("bad scanline"); here zeros run off the file's end
    p = tmp_path / "zero.hdr"
    p.write_bytes(b"#?RADIANCE\n\n-Y 1 +X 8\n\x02\x02\x00\x08" + b"\x00" * 64)
    with pytest.raises(ConfigError, match="zero.hdr"):
        read_hdr(p)


def test_hdr_rle_run_past_the_scanline_is_an_error(tmp_path):
    line = bytes([2, 2, 0, 8]) + bytes([128 + 20, 9]) + (bytes([128 + 8, 9]) * 3)
    p = tmp_path / "overrun.hdr"
    p.write_bytes(b"#?RADIANCE\n\n-Y 1 +X 8\n" + line)
    with pytest.raises(ConfigError, match="overrun.hdr"):
        read_hdr(p)


# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------

def _env_file(tmp_path, name, img):
    p = tmp_path / name
    write_exr(p, {"R": img[..., 0], "G": img[..., 1], "B": img[..., 2]})
    return p


@pytest.mark.parametrize("bad,kind", [(np.nan, "NaN/Inf"), (np.inf, "NaN/Inf"),
                                      (-np.inf, "NaN/Inf"), (-0.5, "negative")])
def test_load_envmap_rejects_bad_texels(tmp_path, bad, kind):
    img = np.ones((5, 9, 3), np.float32)
    img[3, 7, 1] = bad
    p = _env_file(tmp_path, f"bad_{kind[:3]}_{bad}.exr", img)
    with pytest.raises(ConfigError) as info:
        load_envmap(p)
    msg = str(info.value)
    assert str(p.resolve()) in msg and kind in msg and "row 3, column 7" in msg, msg


def test_load_envmap_reports_the_first_bad_texel_and_count(tmp_path):
    img = np.ones((6, 8, 3), np.float32)
    img[4, 2] = np.nan
    img[1, 6, 0] = np.nan
    p = _env_file(tmp_path, "two_nans.exr", img)
    with pytest.raises(ConfigError, match=r"4 NaN/Inf values, first at row 1, column 6"):
        load_envmap(p)


def test_load_envmap_rejects_hdr_with_one_row_or_none(tmp_path):
    p1 = tmp_path / "one_row.exr"
    one = np.ones((1, 8), np.float32)
    write_exr(p1, {"R": one, "G": one, "B": one})
    with pytest.raises(ConfigError, match=r"one_row\.exr.*H >= 2.*\(1, 8, 3\)"):
        load_envmap(p1)
    p0 = tmp_path / "empty.hdr"
    p0.write_bytes(b"#?RADIANCE\n\n-Y 0 +X 4\n")
    with pytest.raises(ConfigError, match=r"empty\.hdr.*\(0, 4, 3\)"):
        load_envmap(p0)
    with pytest.raises(ConfigError, match=r"arr.*\(4, 0, 3\)"):
        validate_texels(np.zeros((4, 0, 3), np.float32), "arr")


# --------------------------------------------------------------------------------------
# Lookup
# --------------------------------------------------------------------------------------

@pytest.fixture
def env():
    rng = np.random.default_rng(4)
    return torch.from_numpy(rng.random((9, 16, 3)) * 3.0)  # float64 (H, W, 3)


def test_direction_to_uv_axes():
    d = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0],
                      [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    uv = direction_to_uv(d)
    assert torch.allclose(uv[:4, 0], torch.tensor([0.0, 0.25, 0.5, 0.75], dtype=torch.float64))
    assert torch.allclose(uv[:4, 1], torch.full((4,), 0.5, dtype=torch.float64))
    assert torch.allclose(uv[4:, 1], torch.tensor([0.0, 1.0], dtype=torch.float64))
    assert ((uv[:, 0] >= 0) & (uv[:, 0] < 1)).all()


def test_lookup_hits_texel_values_at_texel_centers(env):
    h, w, _ = env.shape
    rr, cc = np.meshgrid(np.arange(1, h - 1), np.arange(w), indexing="ij")  # off the poles
    d = torch.from_numpy(texel_dir(cc, rr, h, w))
    got = lookup(env, d)
    assert got.shape == (h - 2, w, 3)
    assert torch.allclose(got, env[1:h - 1], atol=1e-10)
    # float32 too, within float32 rounding
    got32 = lookup(env.float(), d.float())
    assert torch.allclose(got32, env[1:h - 1].float(), atol=1e-4)
    # the poles: rows 0 and H-1 are single points; a constant pole row is returned exactly
    pole = env.clone()
    pole[0] = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    pole[-1] = torch.tensor([4.0, 5.0, 6.0], dtype=torch.float64)
    up_down = torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    assert torch.allclose(lookup(pole, up_down), pole[[0, -1], 0], atol=1e-12)


def test_lookup_is_bilinear_between_centers(env):
    h, w, _ = env.shape
    c, r, fx, fy = 5, 3, 0.3, 0.6
    d = torch.from_numpy(uv_to_dir((c + 0.5 + fx) / w, (r + fy) / (h - 1)))[None]
    want = ((1 - fx) * (1 - fy) * env[r, c] + fx * (1 - fy) * env[r, c + 1]
            + (1 - fx) * fy * env[r + 1, c] + fx * fy * env[r + 1, c + 1])
    assert torch.allclose(lookup(env, d)[0], want, atol=1e-10)
    # unnormalized directions give the same value
    assert torch.allclose(lookup(env, 3.7 * d)[0], want, atol=1e-10)


def test_lookup_wraps_across_the_seam(env):
    h, w, _ = env.shape
    v = 4.3 / (h - 1)
    r0, fy = 4, 0.3
    row = (1 - fy) * env[r0] + fy * env[r0 + 1]  # (W, 3) at that v
    # between the last column's center (u = 1 - 0.5/W) and the first's (u = 0.5/W)
    for u, a in ((0.25 / w, 0.75), (0.0, 0.5), (1.0 - 0.25 / w, 0.25)):
        d = torch.from_numpy(uv_to_dir(u, v))[None]
        want = a * row[0] + (1 - a) * row[w - 1]
        assert torch.allclose(lookup(env, d)[0], want, atol=1e-10), u
    # continuity: just left and just right of u = 0 (the -Z direction)
    eps = 1e-9
    left = lookup(env, torch.from_numpy(uv_to_dir(1.0 - eps, v))[None])
    right = lookup(env, torch.from_numpy(uv_to_dir(eps, v))[None])
    assert (left - right).abs().max() < 1e-6
    # a sweep of u across [0, 1): neighbouring samples never jump
    u = np.linspace(-0.05, 0.05, 201) % 1.0
    vals = lookup(env, torch.from_numpy(uv_to_dir(u, np.full_like(u, v))))
    step = (vals[1:] - vals[:-1]).abs().max()
    assert step < 3.0 * (env.max() - env.min()) * (0.1 / 200) * w


def test_lookup_rotation_about_y(env):
    h, w, _ = env.shape
    rng = np.random.default_rng(5)
    d = torch.from_numpy(rng.normal(size=(50, 3)))
    d = d / d.norm(dim=-1, keepdim=True)
    x, y, z = d.unbind(-1)
    # rotating the map by +90 degrees == rotating the direction by -90 (right-handed, +Y):
    # R_y(-90) (x, y, z) = (-z, y, x)
    d_rot = torch.stack([-z, y, x], -1)
    assert torch.allclose(lookup(env, d, rotate_deg=90.0), lookup(env, d_rot), atol=1e-10)
    # and equals the map shifted by a quarter turn: what was at u sits at u - 1/4 (W % 4 == 0)
    rolled = torch.roll(env, shifts=-w // 4, dims=1)
    assert torch.allclose(lookup(env, d, rotate_deg=90.0), lookup(rolled, d), atol=1e-10)
    # a full turn is the identity, and angles add
    assert torch.allclose(lookup(env, d, rotate_deg=360.0), lookup(env, d), atol=1e-10)
    r30 = lookup(env, d, rotate_deg=30.0)
    assert not torch.allclose(r30, lookup(env, d), atol=1e-3)
    c, s = math.cos(math.radians(-30.0)), math.sin(math.radians(-30.0))
    d30 = torch.stack([c * x + s * z, y, -s * x + c * z], -1)
    assert torch.allclose(r30, lookup(env, d30), atol=1e-10)
    # the feature of texel column 0 seen from world direction rotated by +rotate_deg
    col0 = torch.from_numpy(texel_dir(0, 4, h, w))  # map-frame direction of texel (0, 4)
    cx, sx = math.cos(math.radians(50.0)), math.sin(math.radians(50.0))
    world = torch.stack([cx * col0[0] + sx * col0[2], col0[1], -sx * col0[0] + cx * col0[2]])
    assert torch.allclose(lookup(env, world[None], rotate_deg=50.0)[0], env[4, 0], atol=1e-10)


def test_lookup_scale_and_shapes(env):
    d = torch.randn(2, 5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    base = lookup(env, d)
    assert base.shape == (2, 5, 3)
    assert torch.allclose(lookup(env, d, scale=2.5), 2.5 * base, atol=1e-12)
    assert torch.allclose(lookup(env, d, scale=torch.tensor(0.0, dtype=torch.float64)),
                          torch.zeros_like(base))
    assert (base >= 0).all() and (base <= env.max()).all()  # convex combination of texels


def test_lookup_gradcheck_texels_direction_rotation_scale():
    g = torch.Generator().manual_seed(6)
    tex = (torch.rand(5, 8, 3, dtype=torch.float64, generator=g) + 0.1).requires_grad_()
    # directions away from the poles, the seam (u = 0) and texel center lines (kinks)
    u = torch.tensor([0.13, 0.31, 0.47, 0.62, 0.86], dtype=torch.float64)
    v = torch.tensor([0.33, 0.58, 0.41, 0.71, 0.22], dtype=torch.float64)
    d = torch.from_numpy(uv_to_dir(u.numpy(), v.numpy())) * 1.3
    d.requires_grad_()
    rot = torch.tensor(12.0, dtype=torch.float64, requires_grad=True)
    scale = torch.tensor(1.7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t, dd, r, s: lookup(t, dd, rotate_deg=r, scale=s),
                                    (tex, d, rot, scale), eps=1e-6, atol=1e-5)
    # gradients reach exactly the 4 texels around each sample
    out = lookup(tex, d, rotate_deg=12.0)
    (gt,) = torch.autograd.grad(out[0].sum(), tex)
    assert int((gt.abs().sum(-1) > 0).sum()) == 4
    assert torch.allclose(gt.sum(), torch.tensor(3.0, dtype=torch.float64))  # weights sum to 1


def test_lookup_keeps_the_padded_map_until_it_changes():
    """envmap.lookup keeps its padded copy of a map between calls; an in-place change of
    the map, or a map that needs gradients, is padded anew (no stale or gradient-less
    reads)."""
    from torchrefract.lighting import envmap
    from torchrefract.lighting.envmap import lookup
    tex = torch.rand(8, 16, 3)
    d = torch.randn(200, 3)
    first = lookup(tex, d, 20.0)
    cached = envmap._padded(tex)
    assert envmap._padded(tex) is cached  # reused
    assert torch.equal(lookup(tex, d, 20.0), first)
    tex.mul_(2.0)  # in place: the version counter moves
    assert envmap._padded(tex) is not cached
    assert torch.allclose(lookup(tex, d, 20.0), 2.0 * first)
    g = tex.clone().requires_grad_(True)
    lookup(g, d, 20.0).sum().backward()
    assert g.grad is not None and g.grad.abs().sum() > 0
