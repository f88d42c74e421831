"""Surface samples O_d and their interpolation S_oi (Genevaux et al. 2006, eq. 2, sec. 5.3).

Layout (ours, after sec. 5.3's "regular sampling of all mesh triangles ... according to
some user-supplied rate"): every triangle carries the regular lattice of barycentrics
(n - i - j, i, j) / n, i, j >= 0, i + j <= n, at one rate n for the whole mesh (as the
paper requires, so that shared edges are sampled alike). Lattice points on a shared vertex
or edge are *one* sample, identified topologically: a vertex by its (canonical) index, an
edge point by its two end vertices and its step along the edge, an interior point by its
face. Vertices that coincide in position and shading normal (split only for UVs) are
merged first. A pixel interpolates the three lattice samples of the small triangle it lies
in, barycentrically (the paper's eq. 12; no bilinear cells are needed off the GPU), so the
refraction map is continuous across every edge where the mesh's own shading normals are
continuous; at a hard edge (split normals) it is as discontinuous as the shading itself.

The rate n follows a target sample count: n = max(1, round(sqrt(2 target / F))), since a
closed mesh of F triangles has ~F n^2 / 2 lattice samples; n = 1 (dense meshes) is one
sample per vertex.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from torchrefract.optics.smooth import normalize, tangent_frame


def lattice_rate(num_faces: int, target: int) -> int:
    """The per-triangle rate n giving about ``target`` samples on ``num_faces`` triangles."""
    return max(1, int(math.floor(math.sqrt(2.0 * target / max(num_faces, 1)) + 0.5)))


def lattice_points(n: int) -> np.ndarray:
    """(P, 2) int64 lattice coordinates (i, j), i + j <= n, P = (n + 1)(n + 2) / 2, in the
    order of :func:`lattice_slot`."""
    return np.array([(i, j) for j in range(n + 1) for i in range(n + 1 - j)], dtype=np.int64)


def lattice_slot(i: torch.Tensor, j: torch.Tensor, n: int) -> torch.Tensor:
    """Position of lattice point (i, j) in :func:`lattice_points` (rows j, then i)."""
    return j * (n + 1) - (j * (j - 1)) // 2 + i


@dataclass(frozen=True)
class Layout:
    """The surface samples of one mesh (object space).

    Attributes:
        rate: n, lattice steps per triangle edge.
        lattice: (F, P) int64 sample of each face's lattice point (:func:`lattice_points`).
        position: (S, 3) float32 sample positions.
        frame: (S, 3, 3) float32 rows (tangent, bitangent, normal): the local frame in which
            a sample's view directions are expressed (normal: the interpolated shading
            normal; tangent: :func:`torchrefract.optics.smooth.tangent_frame`).
    """

    rate: int
    lattice: torch.Tensor
    position: torch.Tensor
    frame: torch.Tensor

    @property
    def num_samples(self) -> int:
        return int(self.position.shape[0])


def _canonical_vertices(vertices: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(V,) an id per vertex, equal for vertices with the same position and normal."""
    key = np.ascontiguousarray(np.concatenate([vertices, normals], 1).astype(np.float32))
    _, inverse = np.unique(key.view(np.dtype((np.void, key.dtype.itemsize * 6))).ravel(),
                           return_inverse=True)
    return inverse.reshape(-1).astype(np.int64)


def build_layout(vertices: torch.Tensor, faces: torch.Tensor, normals: torch.Tensor,
                 rate: int) -> Layout:
    """The samples of a mesh at lattice rate ``rate`` (module docstring).

    Args:
        vertices: (V, 3) object-space positions; faces: (F, 3) int64; normals: (V, 3) unit
            shading normals.
        rate: n >= 1.
    """
    v = vertices.double().numpy()
    f = faces.numpy()
    nrm = normals.double().numpy()
    canon = _canonical_vertices(vertices.numpy(), normals.numpy())[f]  # (F, 3)
    pts = lattice_points(rate)  # (P, 2)
    nf, npt = len(f), len(pts)
    w = np.stack([rate - pts[:, 0] - pts[:, 1], pts[:, 0], pts[:, 1]], 1)  # (P, 3) ints
    # Keys (kind, a, b, c): 0 vertex (id); 1 edge (lo id, hi id, steps from lo);
    # 2 interior (face, i, j).
    nz = (w > 0).sum(1)  # (P,)
    keys = np.zeros((nf, npt, 4), dtype=np.int64)
    for p in range(npt):
        corners = np.nonzero(w[p])[0]
        if nz[p] == 1:
            keys[:, p, 0] = 0
            keys[:, p, 1] = canon[:, corners[0]]
        elif nz[p] == 2:
            a, b = canon[:, corners[0]], canon[:, corners[1]]
            wa, wb = w[p, corners[0]], w[p, corners[1]]
            keys[:, p, 0] = 1
            keys[:, p, 1] = np.minimum(a, b)
            keys[:, p, 2] = np.maximum(a, b)
            keys[:, p, 3] = np.where(a < b, wb, wa)  # steps from the lower id
        else:
            keys[:, p, 0] = 2
            keys[:, p, 1] = np.arange(nf)
            keys[:, p, 2:] = pts[p]
    flat = np.ascontiguousarray(keys.reshape(-1, 4))
    _, first, inverse = np.unique(flat.view(np.dtype((np.void, 32))).ravel(),
                                  return_index=True, return_inverse=True)
    lattice = inverse.reshape(nf, npt)
    # Each sample from its first lattice point: position and normal interpolated there.
    fi, pi = np.divmod(first, npt)
    bw = w[pi].astype(np.float64) / rate  # (S, 3)
    pos = (bw[:, :, None] * v[f[fi]]).sum(1)
    nor = (bw[:, :, None] * nrm[f[fi]]).sum(1)
    n_t = normalize(torch.from_numpy(nor).float())
    t, b = tangent_frame(n_t)
    frame = torch.stack([t, b, n_t], 1)  # (S, 3, 3) rows
    return Layout(rate=rate, lattice=torch.from_numpy(lattice.astype(np.int64)),
                  position=torch.from_numpy(pos.astype(np.float32)), frame=frame)


def interpolation(lattice: torch.Tensor, rate: int, face: torch.Tensor, bary: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 2's S_oi at surface points: the three samples around each point and their
    barycentric weights within the lattice's small triangle.

    Args:
        lattice: (F, P) from :class:`Layout`; rate: n.
        face: (N,) int64 mesh-local face; bary: (N, 3) barycentrics (w0, w1, w2).

    Returns:
        samples: (N, 3) int64; weights: (N, 3) float32, >= 0, summing to 1.
    """
    b = bary.clamp(min=0.0)
    b = b / b.sum(-1, keepdim=True).clamp(min=1e-12)
    u, v = b[:, 1] * rate, b[:, 2] * rate
    i = u.floor().long().clamp(0, rate - 1)
    j = v.floor().long().clamp(0, rate - 1)
    over = i + j > rate - 1  # on the far edge: step back into the lattice
    i = torch.where(over, (rate - 1 - j).clamp(min=0), i)
    fu, fv = u - i, v - j
    upper = (fu + fv > 1.0) & (i + j < rate - 1)
    # lower triangle (i, j), (i+1, j), (i, j+1); upper (i+1, j+1), (i, j+1), (i+1, j)
    ia = torch.where(upper, i + 1, i)
    ja = torch.where(upper, j + 1, j)
    pts_i = torch.stack([ia, torch.where(upper, i, i + 1), torch.where(upper, i + 1, i)], 1)
    pts_j = torch.stack([ja, torch.where(upper, j + 1, j), torch.where(upper, j, j + 1)], 1)
    wl = torch.stack([1.0 - fu - fv, fu, fv], 1)
    wu = torch.stack([fu + fv - 1.0, 1.0 - fu, 1.0 - fv], 1)
    wts = torch.where(upper[:, None], wu, wl).clamp(min=0.0)
    wts = wts / wts.sum(-1, keepdim=True).clamp(min=1e-12)
    slots = lattice_slot(pts_i, pts_j, rate)  # (N, 3)
    samples = torch.gather(lattice[face], 1, slots)
    return samples, wts.float()


__all__ = ["Layout", "build_layout", "interpolation", "lattice_points", "lattice_rate",
           "lattice_slot"]
