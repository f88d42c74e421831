"""Sweep configs: one base scene plus swept parameters -> many scenes, deterministically.

A sweep file (``configs/sweep_*.yaml``) names a base scene (a scene YAML in SCENE_SPEC.md form,
or the same mapping inline) and the parameters to vary::

    name: my_sweep
    base: demo.yaml                 # path relative to this file, or an inline scene mapping
    sampling:
      mode: random                  # grid | list | random
      seed: 0
      num_samples: 100              # required for random; a check for grid and list
      repeats: 1                    # grid and list: each point this many times
    sweep:
      mesh:
        path: [../assets/meshes/spot.ply, ../assets/meshes/suzanne.ply]
        random_rotation: yaw        # none | yaw | so3 (uniform over all rotations)
        scale: {uniform: [0.8, 1.1]}
        translate_jitter: 0.05      # uniform in [-j, j]^3
      material:
        roughness: {uniform: [0.0, 0.4]}
        ior: [1.33, 1.5, 1.7]
        distribution: [beckmann, ggx]
      envmap:
        path: [../assets/envmaps/studio_small_03.exr]
        rotate_deg: {uniform: [0, 360]}
        scale: 1.0
      camera:
        orbit:                      # eye on a sphere around the base camera's target
          azimuth_deg: {uniform: [0, 360]}
          elevation_deg: {uniform: [0, 35]}
          distance: {uniform: [2.8, 3.6]}
        look_at_jitter: 0.05        # the point looked at moves uniformly in [-j, j]^3
        yfov_deg: 40
        resolution: [64, "96x64", [128, 96]]   # square size, "WxH" or [W, H]
        samples_per_pixel: 1
      method: [specular]
    relight: false                  # true: samples differing only in the env map are relit
                                    # from one render's matte (torchrefract.dataset.relight)

Every swept value is one of: a scalar (a constant), a list (discrete values), a
``{linspace: [lo, hi, n]}`` (n discrete values), or a distribution ``{uniform: [lo, hi]}`` /
``{log_uniform: [lo, hi]}``.

Sampling:

- ``grid``: the Cartesian product of all discrete axes, in the fixed axis order of
  :data:`AXES` (the last axis varies fastest), each point ``repeats`` times.
- ``list``: the discrete axes zipped (lists of equal length; scalars broadcast).
- ``random``: ``num_samples`` samples; every discrete axis is a uniform choice.

Distribution axes and the random pose / jitter settings are drawn per sample in every mode.
Sample ``i`` draws axis ``a`` from ``numpy.random.default_rng([seed, i, crc32(a)])``: its
values depend only on the seed, its index and the axis, never on the other samples (so a
random sweep can be extended, and a DataLoader worker can draw sample ``i`` alone), and
adding an axis leaves the draws of the others unchanged.

Example:
    >>> from torchrefract.dataset.sweep import load_sweep, expand
    >>> cfg = load_sweep("configs/sweep_demo.yaml")           # doctest: +SKIP
    >>> for sample_id, scene, params in expand(cfg):          # doctest: +SKIP
    ...     print(sample_id, params["material.roughness"])
"""

from __future__ import annotations

import hashlib
import json
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, NamedTuple

import numpy as np

from torchrefract.checks import (
    ConfigError,
    check_choice,
    check_file,
    check_keys,
    check_number,
    load_yaml_file,
    where,
)
from torchrefract.methods import registry
from torchrefract.scene import Scene, scene_from_dict

SAMPLING_MODES = ("grid", "list", "random")
ROTATIONS = ("none", "yaw", "so3")


# --------------------------------------------------------------------------------------
# Config dataclasses
# --------------------------------------------------------------------------------------


MAX_SAMPLES = 1_000_000
"""Most samples one sweep expands into: its plan is made whole before the first render and
again on every resume, in time and memory that grow with the count (docs/datasets.md)."""


@dataclass(frozen=True)
class Axis:
    """One swept parameter: discrete values, or a distribution drawn per sample.

    Exactly one of ``values`` (discrete) and ``dist`` is set.
    """

    values: tuple[Any, ...] | None = None
    """Discrete values (a scalar in the file is a one-value axis)."""
    dist: str | None = None
    """``uniform`` or ``log_uniform`` (between ``low`` and ``high``)."""
    low: float = 0.0
    high: float = 0.0

    @property
    def discrete(self) -> bool:
        return self.values is not None

    def draw(self, rng: np.random.Generator) -> Any:
        """A value of this axis: a uniform choice of the discrete values, or a draw."""
        if self.values is not None:
            return self.values[int(rng.integers(len(self.values)))]
        if self.dist == "uniform":
            return float(rng.uniform(self.low, self.high))
        return float(math.exp(rng.uniform(math.log(self.low), math.log(self.high))))


@dataclass(frozen=True)
class Sampling:
    """How the sweep's axes become samples."""

    mode: str = "grid"
    """``grid`` (Cartesian product), ``list`` (zip) or ``random``."""
    seed: int = 0
    """Seed of every random draw (non-negative integer)."""
    num_samples: int | None = None
    """Number of samples: required for ``random``; for grid/list a check of the count."""
    repeats: int = 1
    """grid/list: each point this many times (with fresh random draws)."""


@dataclass(frozen=True)
class MeshSweep:
    """Meshes and their random pose."""

    path: Axis | None = None
    """Mesh files (relative to the sweep file)."""
    random_rotation: str = "none"
    """``none``, ``yaw`` (uniform about +Y) or ``so3`` (uniform over all rotations); applied
    after the base scene's rotation."""
    scale: Axis | None = None
    """Replaces ``transform.scale``."""
    translate_jitter: float = 0.0
    """Adds a uniform offset in [-j, j]^3 to ``transform.translate``."""


@dataclass(frozen=True)
class MaterialSweep:
    roughness: Axis | None = None
    ior: Axis | None = None
    distribution: Axis | None = None


@dataclass(frozen=True)
class EnvMapSweep:
    path: Axis | None = None
    """Environment maps (relative to the sweep file)."""
    rotate_deg: Axis | None = None
    scale: Axis | None = None


@dataclass(frozen=True)
class OrbitSweep:
    """Camera eye on a sphere about the base camera's target. Azimuth 0 is the +Z side and
    grows towards +X; elevation is up from the XZ plane. Unset axes keep the base camera's
    own azimuth, elevation or distance."""

    azimuth_deg: Axis | None = None
    elevation_deg: Axis | None = None
    distance: Axis | None = None


@dataclass(frozen=True)
class CameraSweep:
    orbit: OrbitSweep | None = None
    look_at_jitter: float = 0.0
    """Moves the point looked at by a uniform offset in [-j, j]^3 (the eye stays)."""
    yfov_deg: Axis | None = None
    resolution: Axis | None = None
    """Values are (width, height) pairs."""
    samples_per_pixel: Axis | None = None


@dataclass(frozen=True)
class SweepSpec:
    mesh: MeshSweep = field(default_factory=MeshSweep)
    material: MaterialSweep = field(default_factory=MaterialSweep)
    envmap: EnvMapSweep = field(default_factory=EnvMapSweep)
    camera: CameraSweep = field(default_factory=CameraSweep)
    method: Axis | None = None


class Sample(NamedTuple):
    """One expanded sample: its id (output stem), its scene and its resolved parameters."""

    sample_id: str
    scene: Scene
    params: dict


@dataclass(frozen=True)
class SweepConfig:
    """A validated sweep: base scene, sampling and swept axes."""

    base: Scene
    """The base scene (paths resolved); every sample starts from it."""
    sampling: Sampling
    sweep: SweepSpec
    name: str = "sweep"
    source: str | None = None
    """The file it was loaded from (for messages)."""
    config_hash: str = ""
    """sha256 of the config's content (and the base scene file's) as canonical JSON."""
    raw: dict = field(default_factory=dict, compare=False, hash=False, repr=False)
    """The config as written (for the dataset's record)."""
    relight: bool = False
    """Relight mode (``relight: true``): samples that differ only in the environment map
    (path, rotation, scale) render their view once with the matte and are relit from it
    (:mod:`torchrefract.dataset.relight`; docs/datasets.md, "Relight mode")."""

    def axes(self) -> list[tuple[str, Axis]]:
        """The set axes in the fixed order (:data:`AXES`)."""
        out = []
        for name, get in _AXIS_GETTERS:
            a = get(self.sweep)
            if a is not None:
                out.append((name, a))
        return out

    def __len__(self) -> int:
        return self.num_samples

    @property
    def num_samples(self) -> int:
        """How many samples the sweep expands into."""
        s = self.sampling
        if s.mode == "random":
            return int(s.num_samples)
        return _num_points(self) * s.repeats

    def sample_id(self, index: int) -> str:
        """The id (output file stem) of sample ``index``: zero-padded, at least 6 digits."""
        width = max(6, len(str(max(self.num_samples - 1, 0))))
        return f"{index:0{width}d}"

    def sample(self, index: int) -> Sample:
        """Sample ``index`` alone (its draws depend only on the seed and the index).

        Raises:
            ConfigError: the index is out of range, or this sample's scene is invalid
                (e.g. a camera looking straight down its up vector); the sample is named.
        """
        if not isinstance(index, (int, np.integer)) or not 0 <= index < self.num_samples:
            raise ConfigError(f"{where(self.source, 'sampling')}: sample index {index!r} out "
                              f"of range [0, {self.num_samples})")
        return _build_sample(self, int(index))

    def samples(self) -> Iterator[Sample]:
        for i in range(self.num_samples):
            yield self.sample(i)


# Fixed axis order: grid order and the order of ``params``. (name, getter).
_AXIS_GETTERS = (
    ("mesh", lambda s: s.mesh.path),
    ("transform.scale", lambda s: s.mesh.scale),
    ("material.roughness", lambda s: s.material.roughness),
    ("material.ior", lambda s: s.material.ior),
    ("material.distribution", lambda s: s.material.distribution),
    ("envmap.path", lambda s: s.envmap.path),
    ("envmap.rotate_deg", lambda s: s.envmap.rotate_deg),
    ("envmap.scale", lambda s: s.envmap.scale),
    ("camera.orbit.azimuth_deg", lambda s: s.camera.orbit and s.camera.orbit.azimuth_deg),
    ("camera.orbit.elevation_deg", lambda s: s.camera.orbit and s.camera.orbit.elevation_deg),
    ("camera.orbit.distance", lambda s: s.camera.orbit and s.camera.orbit.distance),
    ("camera.yfov_deg", lambda s: s.camera.yfov_deg),
    ("camera.resolution", lambda s: s.camera.resolution),
    ("camera.samples_per_pixel", lambda s: s.camera.samples_per_pixel),
    ("method", lambda s: s.method),
)
AXES = tuple(n for n, _ in _AXIS_GETTERS)
"""Names of the sweepable axes, in grid order (also the keys of ``params``)."""


# --------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------

def load_sweep(path: str | Path) -> SweepConfig:
    """Load and validate a sweep YAML file.

    Relative paths (the base scene file, swept meshes and env maps) are resolved against
    the sweep file's directory; those inside a base scene file against that file's.

    Raises:
        ConfigError: missing file, bad YAML, unknown key, bad value or missing asset file,
            naming the file and the key.
    """
    p = Path(path)
    data = load_yaml_file(p, "sweep")
    return sweep_from_dict(data, base_dir=p.parent, source=str(p))


_TOP = ("name", "description", "base", "sampling", "sweep", "relight")


def sweep_from_dict(data: Any, base_dir: str | Path = ".",
                    source: str | None = None) -> SweepConfig:
    """Build a validated :class:`SweepConfig` from plain data (a parsed YAML mapping).

    Raises:
        ConfigError: naming the file, the key and the value of the first problem found.
    """
    base_dir = Path(base_dir)
    check_keys(data, "", _TOP, source, required=("base",))
    name = data.get("name", Path(source).stem if source else "sweep")
    if not isinstance(name, str) or not name:
        raise ConfigError(f"{where(source, 'name')}: expected a non-empty string, got {name!r}")
    if "description" in data and not isinstance(data["description"], str):
        raise ConfigError(f"{where(source, 'description')}: expected a string")
    relight = data.get("relight", False)
    if not isinstance(relight, bool):
        raise ConfigError(f"{where(source, 'relight')}: expected true or false, got "
                          f"{relight!r}")

    sampling = _parse_sampling(data.get("sampling"), source)
    spec = _parse_spec(data.get("sweep"), base_dir, source)

    # Base scene: a scene file, or an inline scene mapping (paths relative to this file).
    base_raw = data["base"]
    hashed: dict[str, Any] = {"config": data}
    if isinstance(base_raw, str):
        base_path = _resolve_file(base_raw, "base", base_dir, source)
        base_data = load_yaml_file(base_path, "base scene")
        scene_dir, scene_src = Path(base_path).parent, base_path
        hashed["base_file"] = base_data
    elif isinstance(base_raw, dict):
        base_data, scene_dir, scene_src = base_raw, base_dir, f"{source or 'sweep'}: base"
    else:
        raise ConfigError(f"{where(source, 'base')}: expected a scene file path or a scene "
                          f"mapping, got {base_raw!r}")
    if not isinstance(base_data, dict):
        raise ConfigError(f"{scene_src}: expected a scene mapping, got {base_data!r}")
    base_data = dict(base_data)
    # A swept mesh or env map may stand in for one the base scene leaves out.
    if "mesh" not in base_data and spec.mesh.path is not None:
        base_data["mesh"] = _first(spec.mesh.path)
    if "envmap" not in base_data and spec.envmap.path is not None:
        base_data["envmap"] = {"path": _first(spec.envmap.path)}
    base = scene_from_dict(base_data, base_dir=scene_dir, source=scene_src, name="base")

    canon = json.dumps(hashed, sort_keys=True, separators=(",", ":"), default=str)
    cfg = SweepConfig(base=base, sampling=sampling, sweep=spec, name=name, source=source,
                      config_hash=hashlib.sha256(canon.encode()).hexdigest(), raw=data,
                      relight=relight)
    _check_counts(cfg)
    return cfg


def _first(axis: Axis) -> str:
    return axis.values[0]


def _parse_sampling(d: Any, source: str | None) -> Sampling:
    d = {} if d is None else d
    check_keys(d, "sampling", ("mode", "seed", "num_samples", "repeats"), source)
    mode = check_choice(d.get("mode", "grid"), "sampling.mode", SAMPLING_MODES, source)
    seed = check_number(d.get("seed", 0), "sampling.seed", source, minimum=0, integer=True)
    n = d.get("num_samples")
    if n is not None:
        n = check_number(n, "sampling.num_samples", source, minimum=1, maximum=MAX_SAMPLES,
                         integer=True)
    elif mode == "random":
        raise ConfigError(f"{where(source, 'sampling.num_samples')}: required when "
                          f"sampling.mode is 'random'")
    repeats = check_number(d.get("repeats", 1), "sampling.repeats", source, minimum=1,
                           integer=True)
    if mode == "random" and "repeats" in d:
        raise ConfigError(f"{where(source, 'sampling.repeats')}: applies to grid and list "
                          f"sampling only (random sampling draws num_samples samples)")
    return Sampling(mode=mode, seed=seed, num_samples=n, repeats=repeats)


def _parse_spec(d: Any, base_dir: Path, source: str | None) -> SweepSpec:
    d = {} if d is None else d
    check_keys(d, "sweep", ("mesh", "material", "envmap", "camera", "method"), source)

    m = {} if d.get("mesh") is None else d["mesh"]
    check_keys(m, "sweep.mesh", ("path", "random_rotation", "scale", "translate_jitter"),
               source)
    mesh = MeshSweep(
        path=_axis(m.get("path"), "sweep.mesh.path", source, kind="file", base_dir=base_dir),
        random_rotation=check_choice(m.get("random_rotation", "none"),
                                     "sweep.mesh.random_rotation", ROTATIONS, source),
        scale=_axis(m.get("scale"), "sweep.mesh.scale", source, minimum=0.0, strict=True),
        translate_jitter=check_number(m.get("translate_jitter", 0.0),
                                      "sweep.mesh.translate_jitter", source, minimum=0.0),
    )

    mat = {} if d.get("material") is None else d["material"]
    check_keys(mat, "sweep.material", ("roughness", "ior", "distribution"), source)
    material = MaterialSweep(
        roughness=_axis(mat.get("roughness"), "sweep.material.roughness", source, minimum=0.0),
        ior=_axis(mat.get("ior"), "sweep.material.ior", source, minimum=0.0, strict=True),
        distribution=_axis(mat.get("distribution"), "sweep.material.distribution", source,
                           kind="choice", choices=("beckmann", "ggx")),
    )

    e = {} if d.get("envmap") is None else d["envmap"]
    check_keys(e, "sweep.envmap", ("path", "rotate_deg", "scale"), source)
    env = EnvMapSweep(
        path=_axis(e.get("path"), "sweep.envmap.path", source, kind="file", base_dir=base_dir),
        rotate_deg=_axis(e.get("rotate_deg"), "sweep.envmap.rotate_deg", source),
        scale=_axis(e.get("scale"), "sweep.envmap.scale", source, minimum=0.0),
    )

    c = {} if d.get("camera") is None else d["camera"]
    check_keys(c, "sweep.camera", ("orbit", "look_at_jitter", "yfov_deg", "resolution",
                                   "samples_per_pixel"), source)
    orbit = None
    if c.get("orbit") is not None:
        o = c["orbit"]
        check_keys(o, "sweep.camera.orbit", ("azimuth_deg", "elevation_deg", "distance"),
                   source)
        orbit = OrbitSweep(
            azimuth_deg=_axis(o.get("azimuth_deg"), "sweep.camera.orbit.azimuth_deg", source),
            # Not +-90: the base camera's up vector would be parallel to the view.
            elevation_deg=_axis(o.get("elevation_deg"), "sweep.camera.orbit.elevation_deg",
                                source, minimum=-89.0, maximum=89.0),
            distance=_axis(o.get("distance"), "sweep.camera.orbit.distance", source,
                           minimum=0.0, strict=True),
        )
    camera = CameraSweep(
        orbit=orbit,
        look_at_jitter=check_number(c.get("look_at_jitter", 0.0), "sweep.camera.look_at_jitter",
                                    source, minimum=0.0),
        yfov_deg=_axis(c.get("yfov_deg"), "sweep.camera.yfov_deg", source, minimum=0.0,
                       maximum=179.0, strict=True),
        resolution=_axis(c.get("resolution"), "sweep.camera.resolution", source,
                         kind="resolution"),
        samples_per_pixel=_axis(c.get("samples_per_pixel"), "sweep.camera.samples_per_pixel",
                                source, kind="int", minimum=1, maximum=16),
    )
    method = _axis(d.get("method"), "sweep.method", source, kind="choice",
                   choices=registry.method_names())
    return SweepSpec(mesh=mesh, material=material, envmap=env, camera=camera, method=method)


def _resolve_file(value: Any, key: str, base_dir: Path, source: str | None) -> str:
    return check_file(value, key, base_dir, source)


def _resolution(v: Any, key: str, source: str | None) -> tuple[int, int]:
    if isinstance(v, str) and "x" in v:
        parts = v.lower().split("x")
        try:
            w, h = (int(x) for x in parts)
        except ValueError:
            raise ConfigError(f"{where(source, key)}: expected 'WIDTHxHEIGHT', got {v!r}") \
                from None
    elif isinstance(v, (list, tuple)):
        if len(v) != 2:
            raise ConfigError(f"{where(source, key)}: expected [width, height], got {v!r}")
        w, h = v
    else:
        w = h = v
    w = check_number(w, key, source, minimum=1, maximum=16384, integer=True)
    h = check_number(h, key, source, minimum=1, maximum=16384, integer=True)
    return (w, h)


def _axis(value: Any, key: str, source: str | None, *, kind: str = "number",
          minimum: float | None = None, maximum: float | None = None, strict: bool = False,
          choices: tuple[str, ...] = (), base_dir: Path = Path(".")) -> Axis | None:
    """Parse one swept value: scalar, list, ``{linspace: ...}`` or a distribution."""
    if value is None:
        return None

    def one(v: Any, k: str) -> Any:
        if kind == "number":
            return check_number(v, k, source, minimum=minimum, maximum=maximum,
                                min_inclusive=not strict)
        if kind == "int":
            return check_number(v, k, source, minimum=minimum, maximum=maximum, integer=True)
        if kind == "file":
            return _resolve_file(v, k, base_dir, source)
        if kind == "choice":
            return check_choice(v, k, choices, source)
        return _resolution(v, k, source)

    if isinstance(value, dict):
        if len(value) != 1:
            raise ConfigError(f"{where(source, key)}: expected one of uniform, log_uniform, "
                              f"linspace (a single key), got {sorted(value)}")
        (dist, args), = value.items()
        if kind != "number" or dist not in ("uniform", "log_uniform", "linspace"):
            allowed = ["uniform", "log_uniform", "linspace"] if kind == "number" else []
            raise ConfigError(f"{where(source, key)}: unknown distribution {dist!r} "
                              f"(allowed here: {allowed or 'a value or a list of values'})")
        k = f"{key}.{dist}"
        n_args = 3 if dist == "linspace" else 2
        if not isinstance(args, (list, tuple)) or len(args) != n_args:
            what = "[lo, hi, n]" if dist == "linspace" else "[lo, hi]"
            raise ConfigError(f"{where(source, k)}: expected {what}, got {args!r}")
        lo, hi = one(args[0], f"{k}[0]"), one(args[1], f"{k}[1]")
        if hi < lo:
            raise ConfigError(f"{where(source, k)}: expected lo <= hi, got {list(args)}")
        if dist == "log_uniform" and lo <= 0:
            raise ConfigError(f"{where(source, k)}: log_uniform needs lo > 0, got {lo}")
        if dist == "linspace":
            n = check_number(args[2], f"{k}[2]", source, minimum=1, maximum=MAX_SAMPLES,
                             integer=True)
            return Axis(values=tuple(float(x) for x in np.linspace(lo, hi, n)))
        return Axis(dist=dist, low=float(lo), high=float(hi))
    # A list is always a list of values: for resolutions, ``[64, 128]`` is two square
    # sizes, and one non-square size is written "64x48" or [[64, 48]].
    if isinstance(value, (list, tuple)):
        if not value:
            raise ConfigError(f"{where(source, key)}: empty list")
        return Axis(values=tuple(one(v, f"{key}[{i}]") for i, v in enumerate(value)))
    return Axis(values=(one(value, key),))


def _num_points(cfg: SweepConfig) -> int:
    sizes = [len(a.values) for _, a in cfg.axes() if a.discrete]
    if cfg.sampling.mode == "grid":
        return int(np.prod(sizes, dtype=np.int64)) if sizes else 1
    return max([n for n in sizes] + [1])  # list: zipped


def _check_counts(cfg: SweepConfig) -> None:
    s, src = cfg.sampling, cfg.source
    if cfg.num_samples > MAX_SAMPLES:
        raise ConfigError(f"{where(src, 'sweep')}: {s.mode} sampling gives "
                          f"{cfg.num_samples:,} samples, more than one sweep takes "
                          f"({MAX_SAMPLES:,}); split it into several sweeps")
    if s.mode == "list":
        lengths = {name: len(a.values) for name, a in cfg.axes() if a.discrete
                   and len(a.values) > 1}
        if len(set(lengths.values())) > 1:
            raise ConfigError(f"{where(src, 'sweep')}: list sampling zips the swept lists, "
                              f"which need equal lengths (or one value); got {lengths}")
    if s.mode != "random" and s.num_samples is not None and s.num_samples != cfg.num_samples:
        raise ConfigError(f"{where(src, 'sampling.num_samples')}: {s.mode} sampling gives "
                          f"{cfg.num_samples} samples, but num_samples is {s.num_samples} "
                          f"(leave it out, or fix it)")


# --------------------------------------------------------------------------------------
# Expansion (pure: the config alone decides every sample)
# --------------------------------------------------------------------------------------

def _rng(seed: int, index: int, stream: str) -> np.random.Generator:
    """The generator of one sample and one axis (independent of every other sample)."""
    return np.random.default_rng([seed, index, zlib.crc32(stream.encode())])


def expand(config: SweepConfig) -> list[Sample]:
    """Every sample of a sweep, in index order: ``[(sample_id, Scene, params), ...]``.

    A pure function of the config: the same config and seed give the same scenes.

    Raises:
        ConfigError: a sample's scene is invalid (the sample is named).
    """
    return list(config.samples())


def _pick(cfg: SweepConfig, index: int) -> dict[str, Any]:
    """The value of every set axis for sample ``index``."""
    s = cfg.sampling
    axes = cfg.axes()
    discrete = [(n, a) for n, a in axes if a.discrete]
    picked: dict[str, Any] = {}
    if s.mode == "grid" and discrete:
        point = index // s.repeats
        coords = np.unravel_index(point, [len(a.values) for _, a in discrete])
        picked.update({n: a.values[int(c)] for (n, a), c in zip(discrete, coords)})
    elif s.mode == "list":
        point = index // s.repeats
        picked.update({n: a.values[point if len(a.values) > 1 else 0] for n, a in discrete})
    for n, a in axes:
        if n not in picked:  # random mode, or a distribution axis in any mode
            picked[n] = a.draw(_rng(s.seed, index, n))
    return {n: picked[n] for n, _ in axes}  # in axis order


def _orbit_of(eye: np.ndarray, target: np.ndarray) -> tuple[float, float, float]:
    v = eye - target
    dist = float(np.linalg.norm(v))
    el = math.degrees(math.asin(max(-1.0, min(1.0, v[1] / dist))))
    az = math.degrees(math.atan2(v[0], v[2]))
    return az, el, dist


def _euler_after(rotate_deg: tuple[float, float, float], extra) -> tuple[float, float, float]:
    """Euler angles (X, then Y, then Z; R = Rz Ry Rx) of ``extra @ R(rotate_deg)``."""
    from scipy.spatial.transform import Rotation  # noqa: PLC0415

    # scipy's lower-case 'xyz' is extrinsic X, then Y, then Z: R = Rz @ Ry @ Rx.
    r = extra * Rotation.from_euler("xyz", rotate_deg, degrees=True)
    return tuple(float(a) for a in r.as_euler("xyz", degrees=True))


def _build_sample(cfg: SweepConfig, index: int) -> Sample:
    sid = cfg.sample_id(index)
    s, spec, base = cfg.sampling, cfg.sweep, cfg.base
    picked = _pick(cfg, index)
    d = base.to_dict()
    params: dict[str, Any] = {"index": index}

    for key, value in picked.items():
        params[key] = list(value) if isinstance(value, tuple) else value
    if "mesh" in picked:
        d["mesh"] = picked["mesh"]
    t = d["transform"]
    if "transform.scale" in picked:
        t["scale"] = picked["transform.scale"]
    if spec.mesh.random_rotation != "none":
        from scipy.spatial.transform import Rotation  # noqa: PLC0415 (slow: only here)

        rng = _rng(s.seed, index, "transform.rotate_deg")
        if spec.mesh.random_rotation == "yaw":
            extra = Rotation.from_euler("y", rng.uniform(0.0, 360.0), degrees=True)
        else:
            extra = Rotation.random(random_state=rng)
        t["rotate_deg"] = _euler_after(tuple(t["rotate_deg"]), extra)
        params["transform.rotate_deg"] = list(t["rotate_deg"])
    if spec.mesh.translate_jitter > 0:
        j = spec.mesh.translate_jitter
        off = _rng(s.seed, index, "transform.translate").uniform(-j, j, 3)
        t["translate"] = tuple(float(a + b) for a, b in zip(t["translate"], off))
        params["transform.translate"] = list(t["translate"])
    for key in ("roughness", "ior", "distribution"):
        if f"material.{key}" in picked:
            d["material"][key] = picked[f"material.{key}"]
    for key in ("path", "rotate_deg", "scale"):
        if f"envmap.{key}" in picked:
            d["envmap"][key] = picked[f"envmap.{key}"]

    c = d["camera"]
    base_eye = np.asarray(base.camera.eye, np.float64)
    base_target = np.asarray(base.camera.target, np.float64)
    if spec.camera.orbit is not None:
        az, el, dist = _orbit_of(base_eye, base_target)
        az = picked.get("camera.orbit.azimuth_deg", az)
        el = picked.get("camera.orbit.elevation_deg", el)
        dist = picked.get("camera.orbit.distance", dist)
        a, e = math.radians(az), math.radians(el)
        direction = np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])
        c["eye"] = tuple(float(x) for x in base_target + dist * direction)
        params["camera.eye"] = list(c["eye"])
    if spec.camera.look_at_jitter > 0:
        j = spec.camera.look_at_jitter
        off = _rng(s.seed, index, "camera.target").uniform(-j, j, 3)
        c["target"] = tuple(float(x) for x in base_target + off)
        params["camera.target"] = list(c["target"])
    if "camera.yfov_deg" in picked:
        c["yfov_deg"] = picked["camera.yfov_deg"]
    if "camera.resolution" in picked:
        c["width"], c["height"] = picked["camera.resolution"]
    if "camera.samples_per_pixel" in picked:
        c["samples_per_pixel"] = picked["camera.samples_per_pixel"]
    if "method" in picked:
        d["method"] = picked["method"]
    d["name"] = sid
    scene = scene_from_dict(d, base_dir="/", source=f"{cfg.source or cfg.name}: sample {sid}",
                            name=sid)
    return Sample(sid, scene, params)
