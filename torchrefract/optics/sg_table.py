"""The SG table's definition and storage: its grid spec (whose key names a fitted table),
the table itself with its per-device caches, and the ``.npz`` file it is shipped and cached
in. Fitted by :mod:`torchrefract.optics.sg_fit`, looked up by :mod:`torchrefract.optics.sgfit`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchrefract.output.atomic import atomic_path

#: Version of the fitting code (:mod:`torchrefract.optics.sg_fit`); part of every table's
#: cache key.
FIT_VERSION = 1
#: Largest sharpness stored (a Dirac lobe, e.g. transmission at ``eta == 1``).
K_MAX = 1e9
#: Smallest sharpness stored.
K_MIN = 1e-3
#: Lobes with less energy than this are treated as absent (TIR; ``eta == 1`` reflection).
ENERGY_EPS = 1e-6
#: ``cos theta_o`` used for the grazing node ``theta_o = 90`` degrees.
COS_GRAZING = 1e-4

DISTRIBUTIONS = ("beckmann", "ggx")
LOBES = ("transmit", "reflect")
CHANNELS = ("energy", "log_sharpness", "axis_polar_angle", "log_sharpness_l2")

DATA_DIR = Path(__file__).resolve().parent.parent / "tables"
SHIPPED_TABLE = DATA_DIR / "sg_table_v1.npz"


@dataclass(frozen=True)
class SGTableSpec:
    """Axes and quadrature of an SG table (every field is part of the cache key).

    Attributes:
        n_theta: nodes of ``theta_o``, uniform in [0, 90] degrees.
        n_eta: nodes of ``eta``, log-spaced in ``[1/eta_max, eta_max]``; odd so 1 is a node.
        eta_max: largest relative index (the smallest is its inverse).
        n_alpha: nodes of ``alpha``, log-spaced in ``[alpha_min, alpha_max]``.
        alpha_min: smallest tabulated roughness.
        alpha_max: largest tabulated roughness.
        quad_h: step of the quadrature in ``x = log(tan(theta_m) / alpha)``.
        quad_nphi: quadrature columns over ``phi_m in [0, pi]``.
        quad_x_min: lower end of ``x`` (the NDF mass below it is < 1e-5).
        quad_tan_max: largest ``tan(theta_m)`` integrated for GGX (Beckmann stops at
            ``x = 2``, where ``D`` is below ``exp(-54)`` of its peak).
    """

    n_theta: int = 48
    n_eta: int = 33
    eta_max: float = 3.0
    n_alpha: int = 24
    alpha_min: float = 1e-3
    alpha_max: float = 1.0
    quad_h: float = 0.1
    quad_nphi: int = 64
    quad_x_min: float = -6.5
    quad_tan_max: float = 1e3

    def __post_init__(self) -> None:
        if self.n_eta % 2 != 1 or self.n_eta < 3:
            raise ValueError(f"SGTableSpec.n_eta must be odd and >= 3, got {self.n_eta}")
        if self.n_theta < 2 or self.n_alpha < 2:
            raise ValueError("SGTableSpec.n_theta and n_alpha must be >= 2")
        if not (self.eta_max > 1.0 and 0.0 < self.alpha_min < self.alpha_max):
            raise ValueError(f"SGTableSpec: bad ranges in {self}")

    def key(self) -> str:
        """Hash of the fields and :data:`FIT_VERSION` (names the cache file)."""
        blob = json.dumps({"fit_version": FIT_VERSION, **dataclasses.asdict(self)},
                          sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def theta_nodes(self) -> np.ndarray:
        """(T,) polar angles of the view direction, radians."""
        return np.linspace(0.0, 0.5 * math.pi, self.n_theta)

    def eta_nodes(self) -> np.ndarray:
        """(E,) relative indices; node ``E // 2`` is exactly 1, node ``E-1-i`` is ``1/node i``."""
        h = self.n_eta // 2
        low = np.exp(np.linspace(-math.log(self.eta_max), 0.0, h + 1)[:-1])
        return np.concatenate([low, [1.0], (1.0 / low)[::-1]])

    def alpha_nodes(self) -> np.ndarray:
        """(A,) roughness values."""
        return np.exp(np.linspace(math.log(self.alpha_min), math.log(self.alpha_max),
                                  self.n_alpha))


@dataclass
class SGTable:
    """A loaded table. ``data``: float32 ``(2, 2, T, E, A, 4)`` (see the module docstring)."""

    spec: SGTableSpec
    data: torch.Tensor
    build_seconds: float = float("nan")
    _cache: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    @property
    def theta(self) -> np.ndarray:
        return self.spec.theta_nodes()

    @property
    def eta(self) -> np.ndarray:
        return self.spec.eta_nodes()

    @property
    def alpha(self) -> np.ndarray:
        return self.spec.alpha_nodes()

    def to(self, device: torch.device | str) -> "SGTable":
        return SGTable(self.spec, self.data.to(device), self.build_seconds)

    def volume(self, dtype: torch.dtype, device: torch.device | str,
               sharpness: str = "moment") -> torch.Tensor:
        """``(2 * 2, 3, T, E, A)`` volumes (index ``2 * distribution + lobe``) of energy,
        log k and sin(axis angle), for ``grid_sample`` (memoized)."""
        key = ("volume", dtype, str(device), sharpness)
        if key not in self._cache:
            ch = (0, 1 if sharpness == "moment" else 3, 2)
            # the channels picked before widening (exact): no float64 copy of all four
            d = self.data[..., list(ch)].to(dtype=torch.float64)  # (2, 2, T, E, A, 3)
            d[..., 2] = torch.sin(d[..., 2])
            self._cache[key] = d.flatten(0, 1).permute(0, 4, 1, 2, 3).to(
                device=device, dtype=dtype).contiguous()
        return self._cache[key]

    def energy_volume(self, dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
        """``(2, 2, T, E, A)`` volumes (distribution, lobe) of the energy alone (memoized)."""
        key = ("energy", dtype, str(device))
        if key not in self._cache:
            self._cache[key] = self.data[..., 0].to(device=device, dtype=dtype).contiguous()
        return self._cache[key]

    def energy_change_volume(self, dtype: torch.dtype, device: torch.device | str
                             ) -> torch.Tensor:
        """``(2, 2, T, E, A)``: the energy less its value at the smallest roughness (the first
        node of the last axis), the change the roughness makes (memoized). Interpolation is
        linear, so one lookup of it is the difference of two lookups of the energy."""
        key = ("energy_change", dtype, str(device))
        if key not in self._cache:
            e = self.data[..., 0].to(dtype=torch.float64)
            self._cache[key] = (e - e[..., :1]).to(device=device, dtype=dtype).contiguous()
        return self._cache[key]


# --------------------------------------------------------------------------------------
# Storage and caching
# --------------------------------------------------------------------------------------

def save_sg_table(table: SGTable, path: str | Path) -> Path:
    """Write a table as a compressed ``.npz`` (float32 data, axes, spec, key)."""
    path = Path(path)
    # The temporary name ends in .npz, which np.savez_compressed would otherwise append.
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(
            str(tmp), data=table.data.cpu().numpy().astype(np.float32),
            theta=table.theta, eta=table.eta, alpha=table.alpha,
            spec=json.dumps(dataclasses.asdict(table.spec)), key=table.spec.key(),
            fit_version=FIT_VERSION, build_seconds=table.build_seconds,
            distributions=np.array(DISTRIBUTIONS), lobes=np.array(LOBES),
            channels=np.array(CHANNELS))
    return path


def read_sg_table(path: str | Path) -> SGTable:
    """Read a table written by :func:`save_sg_table` (no key check)."""
    with np.load(path, allow_pickle=False) as z:
        spec = SGTableSpec(**json.loads(str(z["spec"])))
        data = torch.from_numpy(np.array(z["data"], dtype=np.float32))
        secs = float(z["build_seconds"]) if "build_seconds" in z else float("nan")
        if str(z["key"]) != spec.key():
            raise ValueError(f"{path}: stored key {z['key']} does not match its spec "
                             f"({spec.key()}; fitting code version {FIT_VERSION})")
    return SGTable(spec, data, secs)


__all__ = ["CHANNELS", "COS_GRAZING", "DISTRIBUTIONS", "ENERGY_EPS", "FIT_VERSION", "K_MAX",
           "K_MIN", "LOBES", "SHIPPED_TABLE", "SGTable", "SGTableSpec", "read_sg_table",
           "save_sg_table"]
