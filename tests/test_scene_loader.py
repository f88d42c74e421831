"""The strict scene loader: the shipped demo, and every kind of bad input named precisely.

Each error must be a ConfigError whose message names the YAML file, the key and the value.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from pathlib import Path

import pytest
import yaml

import torchrefract as tr
from torchrefract import ConfigError, EnvMap, Scene, load_scene, scene_from_dict

ROOT = Path(__file__).resolve().parents[1]
MESH = ROOT / "assets" / "meshes" / "spot.ply"
ENV = ROOT / "assets" / "envmaps" / "studio_small_03.exr"


def base(tmp_path: Path) -> dict:
    """A valid scene whose asset paths are relative to a YAML file in tmp_path."""
    return {
        "mesh": os.path.relpath(MESH, tmp_path),
        "envmap": {"path": os.path.relpath(ENV, tmp_path), "scale": 1.0, "rotate_deg": 0},
        "material": {"ior": 1.5, "roughness": 0.1},
        "camera": {"eye": [0, 0, 4], "target": [0, 0, 0], "up": [0, 1, 0], "width": 32,
                   "height": 24},
        "method": "specular",
    }


def write(tmp_path: Path, data, name: str = "scene.yaml") -> Path:
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return p


def expect_error(path: Path, *fragments: str) -> str:
    with pytest.raises(ConfigError) as info:
        load_scene(path)
    msg = str(info.value)
    for frag in (str(path),) + fragments:
        assert frag in msg, f"{frag!r} not in error message {msg!r}"
    return msg


# --------------------------------------------------------------------------------------
# Valid scenes
# --------------------------------------------------------------------------------------

def test_demo_yaml_loads_with_resolved_paths_and_values():
    path = ROOT / "configs" / "demo.yaml"
    s = load_scene(path)
    assert s.name == "demo"
    assert s.mesh == str(MESH.resolve())
    assert s.envmap.path == str(ENV.resolve())
    assert Path(s.mesh).is_file() and Path(s.envmap.path).is_file()
    raw = yaml.safe_load(path.read_text())  # the loader keeps every value of the file
    assert s.transform.rotate_deg == tuple(float(x) for x in raw["transform"]["rotate_deg"])
    assert s.transform.scale == raw["transform"]["scale"]
    assert s.material.ior == raw["material"]["ior"]
    assert s.material.roughness == raw["material"]["roughness"]
    assert s.material.distribution == raw["material"]["distribution"]
    assert s.material.absorption == tuple(raw["material"]["absorption"])
    assert s.envmap.rotate_deg == raw["envmap"]["rotate_deg"]
    assert s.lights == ()
    c = s.camera
    assert c.eye == tuple(raw["camera"]["eye"]) and c.up == (0.0, 1.0, 0.0)
    assert (c.yfov_deg, c.width, c.height, c.samples_per_pixel) == tuple(
        raw["camera"][k] for k in ("yfov_deg", "width", "height", "samples_per_pixel"))
    assert isinstance(c.width, int) and isinstance(c.samples_per_pixel, int)
    assert s.method == raw["method"] == "rousiers" and s.method_options == {}
    # the resolved scene is plain data that loads back to the same scene
    d = s.to_dict()
    yaml.safe_dump(d)  # plain types only
    assert scene_from_dict(d, base_dir="/", name="demo") == s


def test_paths_are_relative_to_the_yaml_file_not_the_cwd(tmp_path, monkeypatch):
    sub = tmp_path / "scenes" / "deep"
    (sub / "assets").mkdir(parents=True)
    (sub / "assets" / "m.ply").write_bytes(MESH.read_bytes())
    (tmp_path / "env.exr").write_bytes(ENV.read_bytes())
    data = base(tmp_path)
    data["mesh"] = "assets/m.ply"
    data["envmap"] = "../../env.exr"  # shorthand form: envmap: PATH
    p = write(sub, data, "my_scene.yaml")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    s = load_scene(p)
    assert s.mesh == str((sub / "assets" / "m.ply").resolve())
    assert s.envmap.path == str((tmp_path / "env.exr").resolve())
    assert s.name == "my_scene"
    # absolute paths work as given
    data["mesh"] = str(MESH)
    s2 = load_scene(write(sub, data, "abs.yaml"))
    assert s2.mesh == str(MESH.resolve())
    # and the same relative path from a file elsewhere is not found
    data["mesh"] = "assets/m.ply"
    expect_error(write(tmp_path, data, "wrong_dir.yaml"), "mesh", "'assets/m.ply'",
                 "file not found")


def test_minimal_yaml_equals_dataclass_defaults(tmp_path):
    p = write(tmp_path, {"mesh": str(MESH), "envmap": str(ENV)}, "minimal.yaml")
    loaded = load_scene(p)
    built = Scene(mesh=str(MESH.resolve()), envmap=EnvMap(path=str(ENV.resolve())),
                  name="minimal")
    assert loaded == built
    # defaults of SCENE_SPEC.md
    assert built.material == tr.Material(ior=1.5, roughness=0.1, distribution="beckmann",
                                         roughness_map=None, roughness_range=(0.02, 0.5),
                                         absorption=(0.0, 0.0, 0.0))
    assert built.transform == tr.Transform(1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert built.camera == tr.Camera(eye=(0.0, 0.0, 4.0), target=(0.0, 0.0, 0.0),
                                     up=(0.0, 1.0, 0.0), yfov_deg=40.0, width=256,
                                     height=256, samples_per_pixel=1)
    assert (built.envmap.scale, built.envmap.rotate_deg) == (1.0, 0.0)


def test_scene_dataclass_constructor():
    s = Scene(mesh=str(MESH), envmap=EnvMap(path=str(ENV), rotate_deg=30.0),
              material=tr.Material(ior=1.33, roughness=0.2, distribution="ggx"),
              lights=(tr.SphereLight(position=(1.0, 2.0, 3.0), radius=0.5,
                                     radiance=(4.0, 4.0, 4.0)),),
              camera=tr.Camera(width=40, height=30), method_options={"tir": "reflect"})
    assert s.envmap.rotate_deg == 30.0 and s.material.distribution == "ggx"
    assert s.camera.width == 40 and s.camera.yfov_deg == 40.0  # others default
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.mesh = "other.ply"  # type: ignore[misc]
    s2 = s.replace(material=tr.Material(ior=2.0))
    assert s2.material.ior == 2.0 and s.material.ior == 1.33
    assert s2.camera is s.camera
    with pytest.raises(TypeError):
        Scene(mesh=str(MESH))  # envmap is required
    d = s.to_dict()
    assert d["lights"] == [{"position": (1.0, 2.0, 3.0), "radius": 0.5,
                            "radiance": (4.0, 4.0, 4.0)}]
    assert d["camera"]["width"] == 40 and d["envmap"]["path"] == str(ENV)
    # to_dict -> scene_from_dict validates and reproduces the scene (paths are absolute)
    assert scene_from_dict(d, name="scene") == s.replace(
        mesh=str(MESH.resolve()), envmap=dataclasses.replace(s.envmap,
                                                             path=str(ENV.resolve())))


def test_lights_and_method_options_load(tmp_path):
    data = base(tmp_path)
    data["lights"] = [{"position": [1, 2, 3], "radius": 0.25, "radiance": [5, 4, 3]}]
    data["method_options"] = {"tir": "reflect", "march_steps": 32}
    s = load_scene(write(tmp_path, data))
    assert s.lights == (tr.SphereLight((1.0, 2.0, 3.0), 0.25, (5.0, 4.0, 3.0)),)
    assert s.method_options == {"tir": "reflect", "march_steps": 32}


# --------------------------------------------------------------------------------------
# Errors: file, key and value named
# --------------------------------------------------------------------------------------

def _set(data: dict, dotted: str, value):
    d = data
    *parents, last = dotted.split(".")
    for k in parents:
        d = d.setdefault(k, {})
    d[last] = value
    return data


BAD_VALUES = [
    # (key, value, fragments expected in the message besides the file)
    ("camera.width", "big", ("camera.width", "'big'", "integer")),
    ("camera.width", 2.5, ("camera.width", "2.5", "integer")),
    ("camera.height", 0, ("camera.height", ">= 1", "0")),
    ("camera.samples_per_pixel", True, ("camera.samples_per_pixel", "True")),
    ("camera.yfov_deg", 180, ("camera.yfov_deg", "180")),
    ("camera.eye", [0, 1], ("camera.eye", "3 numbers", "[0, 1]")),
    ("camera.eye", "origin", ("camera.eye", "'origin'")),
    ("material.roughness", -0.1, ("material.roughness", ">= 0", "-0.1")),
    ("material.ior", -1.5, ("material.ior", "> 0", "-1.5")),
    ("material.ior", 0, ("material.ior", "> 0", "got 0")),
    ("material.distribution", "phong", ("material.distribution", "'phong'", "beckmann")),
    ("material.roughness_range", [0.5, 0.1], ("material.roughness_range", "0.5", "0.1")),
    ("material.absorption", [0, -1, 0], ("material.absorption[1]", "-1")),
    ("transform.scale", 0, ("transform.scale", "> 0", "got 0")),
    ("transform.rotate_deg", [0, "x", 0], ("transform.rotate_deg[1]", "'x'")),
    ("envmap.scale", -2, ("envmap.scale", "-2")),
    ("method", "magic", ("method", "'magic'", "specular")),
    ("exposure", "bright", ("exposure", "'bright'")),
]


@pytest.mark.parametrize("key,value,fragments", BAD_VALUES,
                         ids=[f"{k}={v!r}" for k, v, _ in BAD_VALUES])
def test_bad_value_is_named(tmp_path, key, value, fragments):
    p = write(tmp_path, _set(base(tmp_path), key, value))
    expect_error(p, *fragments)


NAN_CASES = [
    # (key to set, literal YAML, key named in the message, value shown)
    ("material.ior", ".nan", "material.ior", "nan"),
    ("material.roughness", ".inf", "material.roughness", "inf"),
    ("camera.eye.1", ".nan", "camera.eye[1]", "nan"),
    ("envmap.rotate_deg", "-.inf", "envmap.rotate_deg", "-inf"),
    ("lights.0.radius", ".NaN", "lights[0].radius", "nan"),
    ("exposure", ".nan", "exposure", "nan"),
]
SENTINEL = 12345.678  # written by yaml.safe_dump as 12345.678, then replaced in the text


@pytest.mark.parametrize("key,literal,named,shown", NAN_CASES,
                         ids=[f"{c[0]}={c[1]}" for c in NAN_CASES])
def test_nan_and_inf_in_yaml_are_rejected(tmp_path, key, literal, named, shown):
    data = base(tmp_path)
    data["lights"] = [{"position": [1, 1, 1], "radius": 0.1, "radiance": [1, 1, 1]}]
    *parents, last = key.split(".")
    d = data
    for k in parents:
        d = d[int(k)] if k.isdigit() else d.setdefault(k, {})
    if last.isdigit():
        d[int(last)] = SENTINEL
    else:
        d[last] = SENTINEL
    text = yaml.safe_dump(data)
    assert text.count(str(SENTINEL)) == 1
    p = write(tmp_path, text.replace(str(SENTINEL), literal))
    expect_error(p, named, shown, "finite")


def test_unknown_top_level_key(tmp_path):
    data = base(tmp_path)
    data["meshh"] = "typo.ply"
    expect_error(write(tmp_path, data), "unknown key", "'meshh'")


def test_unknown_nested_key(tmp_path):
    data = base(tmp_path)
    data["camera"]["fov"] = 45
    msg = expect_error(write(tmp_path, data), "camera", "unknown key", "'fov'")
    assert "yfov_deg" in msg  # the allowed keys are listed


def test_unknown_key_in_material_and_light(tmp_path):
    data = base(tmp_path)
    data["material"]["roughnes"] = 0.2
    expect_error(write(tmp_path, data), "material", "'roughnes'")
    data = base(tmp_path)
    data["lights"] = [{"position": [0, 2, 0], "radius": 0.1, "radiance": [1, 1, 1],
                       "color": [1, 0, 0]}]
    expect_error(write(tmp_path, data), "lights[0]", "'color'")


def test_missing_mesh_file(tmp_path):
    data = base(tmp_path)
    data["mesh"] = "meshes/nope.ply"
    msg = expect_error(write(tmp_path, data), "mesh", "'meshes/nope.ply'", "not found")
    assert str(tmp_path / "meshes" / "nope.ply") in msg  # where it looked


def test_missing_envmap_file(tmp_path):
    data = base(tmp_path)
    data["envmap"]["path"] = "missing.exr"
    msg = expect_error(write(tmp_path, data), "envmap.path", "'missing.exr'", "not found")
    assert str(tmp_path / "missing.exr") in msg


def test_missing_required_keys(tmp_path):
    data = base(tmp_path)
    del data["envmap"]
    expect_error(write(tmp_path, data), "missing required key", "'envmap'")
    data = base(tmp_path)
    del data["envmap"]["path"]
    expect_error(write(tmp_path, data), "envmap", "missing required key", "'path'")


def test_camera_eye_equals_target(tmp_path):
    data = base(tmp_path)
    data["camera"]["eye"] = [1, 2, 3]
    data["camera"]["target"] = [1, 2, 3]
    expect_error(write(tmp_path, data), "camera.target", "camera.eye", "[1.0, 2.0, 3.0]")


@pytest.mark.parametrize("up", [[0, 0, 1], [0, 0, -2.5], [0, 0, 0]])
def test_camera_up_parallel_to_view(tmp_path, up):
    data = base(tmp_path)  # eye (0, 0, 4) looking at the origin: view along -Z
    data["camera"]["up"] = up
    expect_error(write(tmp_path, data), "camera.up", str([float(x) for x in up]), "parallel")


def test_camera_up_slightly_off_view_is_accepted(tmp_path):
    data = base(tmp_path)
    data["camera"]["up"] = [0, 1e-3, 1]
    assert load_scene(write(tmp_path, data)).camera.up == (0.0, 1e-3, 1.0)


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n"])
def test_empty_yaml_file(tmp_path, text):
    expect_error(write(tmp_path, text), "empty")


def test_yaml_that_is_not_a_mapping(tmp_path):
    expect_error(write(tmp_path, "- mesh.ply\n- env.exr\n"), "expected a mapping",
                 "['mesh.ply', 'env.exr']")


def test_invalid_yaml(tmp_path):
    msg = expect_error(write(tmp_path, "mesh: [unclosed\ncamera: {width: 3\n"),
                       "not valid YAML")
    assert "line" in msg  # the parser's position is kept


def test_missing_scene_file(tmp_path):
    p = tmp_path / "absent.yaml"
    with pytest.raises(ConfigError, match="absent.yaml"):
        load_scene(p)


def test_light_missing_radius(tmp_path):
    data = base(tmp_path)
    data["lights"] = [{"position": [0, 2, 0], "radiance": [1, 1, 1]}]
    expect_error(write(tmp_path, data), "lights[0]", "missing required key", "'radius'")
    data["lights"] = [{"position": [0, 2, 0], "radius": 0, "radiance": [1, 1, 1]}]
    expect_error(write(tmp_path, data), "lights[0].radius", "> 0", "got 0")
    data["lights"] = {"position": [0, 2, 0]}
    expect_error(write(tmp_path, data), "lights", "expected a list")


def test_config_error_is_a_value_error():
    assert issubclass(ConfigError, ValueError)


# --------------------------------------------------------------------------------------
# Method and method_options (validated by torchrefract.render before any work is done)
# --------------------------------------------------------------------------------------

def test_render_rejects_unknown_method(tmp_path):
    s = load_scene(write(tmp_path, base(tmp_path), "meth.yaml"))
    with pytest.raises(ConfigError, match=r"unknown method 'magic'.*specular"):
        tr.render([s], method="magic")


def test_unknown_method_option_is_rejected_naming_the_file(tmp_path):
    data = base(tmp_path)
    data["method_options"] = {"bounces": 3}
    path = write(tmp_path, data, "opts_scene.yaml")
    with pytest.raises(ConfigError) as info:
        load_scene(path)
    msg = str(info.value)
    # the message names the file, the key, the method and the allowed keys
    for frag in (str(path), "method_options", "'bounces'", "specular", "tir"):
        assert frag in msg, (frag, msg)
    # A scene built in Python is checked the same way when rendered.
    s = load_scene(write(tmp_path, base(tmp_path), "ok.yaml")).replace(
        method_options={"bounces": 3})
    with pytest.raises(ConfigError, match="'bounces'"):
        tr.render([s])


@pytest.mark.parametrize("opts,fragments", [
    ({"tir": "bounce"}, ("method_options.tir", "'bounce'", "clamp")),
    ({"march_steps": 0}, ("method_options.march_steps", ">= 1", "0")),
    ({"refine_steps": 2.5}, ("method_options.refine_steps", "2.5")),
])
def test_bad_method_option_values_are_rejected(tmp_path, opts, fragments):
    data = base(tmp_path)
    data["method_options"] = opts
    with pytest.raises(ConfigError) as info:
        load_scene(write(tmp_path, data, "bad_opts.yaml"))
    for frag in ("bad_opts.yaml",) + fragments:
        assert frag in str(info.value), (frag, str(info.value))


def test_specular_options_parse_valid_values():
    from torchrefract.methods import registry
    from torchrefract.methods.specular import SpecularOptions

    parse = registry.get("specular").parse
    o = parse({"tir": "reflect", "march_steps": 16}, "x.yaml")
    assert o == SpecularOptions(tir="reflect", march_steps=16, refine_steps=10)
    assert parse({}) == SpecularOptions()
    with pytest.raises(ConfigError, match=r"x\.yaml: method_options: unknown key 'foo'"):
        parse({"foo": 1}, "x.yaml")


def test_scene_from_dict_names_source_and_does_not_touch_input(tmp_path):
    data = base(tmp_path)
    frozen = copy.deepcopy(data)
    s = scene_from_dict(data, base_dir=tmp_path, source="inline.yaml", name="inl")
    assert data == frozen and s.name == "inl"
    data["camera"]["width"] = -4
    with pytest.raises(ConfigError, match=r"^inline\.yaml: camera\.width: .*-4"):
        scene_from_dict(data, base_dir=tmp_path, source="inline.yaml")


def test_scenes_built_in_python_are_validated_on_render(tmp_path):
    s = load_scene(write(tmp_path, base(tmp_path)))
    bad = s.replace(material=tr.Material(ior=-1.0))
    with pytest.raises(ConfigError, match=r"material\.ior.*-1\.0"):
        tr.render([bad])
    cam = tr.Camera(eye=(1.0, 2.0, 3.0), target=(1.0, 2.0, 3.0))
    with pytest.raises(ConfigError, match="camera.target"):
        tr.render([s.replace(camera=cam)])


def test_validation_is_remembered_per_object_but_sees_changed_options(tmp_path):
    from torchrefract.scene.loader import validate

    s = load_scene(write(tmp_path, base(tmp_path))).replace(method="rousiers",
                                                            method_options={})
    first = validate(s)
    assert validate(s) is first  # the same object again: checked once
    as_spec = validate(s, "specular")
    assert as_spec.method == "specular" and validate(s).method == "rousiers"
    s.method_options["no_such_option"] = 1  # a dict field changed in place is checked anew
    with pytest.raises(ConfigError, match="no_such_option"):
        validate(s)


def test_new_scenes_differing_by_their_cameras_are_checked_as_a_whole(tmp_path):
    """A new scene object whose fields but the camera were checked before (a dataset's
    next view) gets only its camera checked again: the result equals a full check, a bad
    camera is still refused, and any other changed field is checked in full."""
    from torchrefract.scene.loader import validate

    s = load_scene(write(tmp_path, base(tmp_path)))
    validate(s)
    moved = s.replace(camera=dataclasses.replace(s.camera, eye=(0.5, 0.25, 3.0), width=7))
    assert validate(moved) == scene_from_dict(moved.to_dict(), name=moved.name)
    assert validate(moved).camera.width == 7
    with pytest.raises(ConfigError, match=r"camera\.yfov_deg.*nan"):
        validate(s.replace(camera=dataclasses.replace(s.camera, yfov_deg=float("nan"))))
    with pytest.raises(ConfigError, match=r"camera\.up"):
        validate(s.replace(camera=dataclasses.replace(s.camera, up=(0.0, 0.0, 0.0))))
    with pytest.raises(ConfigError, match=r"material\.roughness"):
        validate(moved.replace(material=dataclasses.replace(s.material, roughness=-0.5)))


def test_name_key_sets_the_output_stem_and_is_checked(tmp_path):
    data = base(tmp_path)
    data["name"] = "custom"
    assert load_scene(write(tmp_path, data)).name == "custom"
    data["name"] = 5
    expect_error(write(tmp_path, data, "n.yaml"), "name", "5")
    data.pop("name")
    data["transform"] = []
    expect_error(write(tmp_path, data, "t.yaml"), "transform", "[]")


def test_a_key_given_twice_is_refused_with_its_line(tmp_path):
    """YAML lets the last of two equal keys win without a word; a scene file refuses it."""
    text = yaml.safe_dump(base(tmp_path)) + "camera: {width: 8}\n"
    msg = expect_error(write(tmp_path, text), "'camera' given twice", "line")
    assert "line" in msg


def test_a_number_yaml_reads_as_text_gets_a_hint(tmp_path):
    """PyYAML reads ``1e-3`` (no dot) as a string: the error says how to write it."""
    text = yaml.safe_dump(base(tmp_path)).replace("roughness: 0.1", "roughness: 1e-3")
    expect_error(write(tmp_path, text), "material.roughness", "'1e-3'", "write 1.0e-3")


def test_names_that_cannot_be_file_names_are_refused(tmp_path):
    """A ``name`` becomes the output files' stem: a NUL or more than 250 bytes (with
    ``.json`` past a file name's 255) is refused up front, naming the key."""
    data = base(tmp_path)
    data["name"] = "a\0b"
    expect_error(write(tmp_path, data), "name", "NUL")
    data["name"] = "n" * 251
    expect_error(write(tmp_path, data), "name", "250 bytes")
    data["name"] = "n" * 250
    assert load_scene(write(tmp_path, data)).name == "n" * 250


def test_integers_that_are_nan_or_infinite_are_named(tmp_path):
    """NaN and infinity in an integer field fail as in any number field (not as Python's
    own conversion error)."""
    for key, value in (("width", float("nan")), ("samples_per_pixel", float("inf"))):
        data = base(tmp_path)
        data["camera"][key] = value
        expect_error(write(tmp_path, data), f"camera.{key}", "finite")
    data = base(tmp_path)
    data["method_options"] = {"march_steps": float("inf")}
    expect_error(write(tmp_path, data), "method_options.march_steps", "finite")


def test_radiance_beyond_the_limit_is_refused(tmp_path):
    """Light radiance and ``envmap.scale`` are bounded (``checks.RADIANCE_LIMIT``) so that
    no product of them overflows float32 on the way to the image."""
    data = base(tmp_path)
    data["envmap"]["scale"] = 3e38
    expect_error(write(tmp_path, data), "envmap.scale", "1e+15")
    data = base(tmp_path)
    data["lights"] = [{"position": [1, 1, 1], "radius": 0.1, "radiance": [1.7e38, 1, 1]}]
    expect_error(write(tmp_path, data), "lights[0].radiance[0]", "1e+15")


def test_python_scenes_take_paths_and_name_wrong_parts(tmp_path):
    """A scene built in Python may name its files with ``pathlib.Path``; a part of the
    wrong type (one light instead of a list, ``camera=None``) is a ConfigError naming it,
    whatever was validated before."""
    s = Scene(mesh=MESH, envmap=EnvMap(path=ENV), camera=tr.Camera(width=8, height=8))
    from torchrefract.scene.loader import validate

    assert validate(s).mesh == str(MESH.resolve())
    assert validate(s.replace(envmap=ENV)).envmap.path == str(ENV.resolve())  # shorthand
    with pytest.raises(ConfigError, match=r"lights: expected a list of torchrefract\.Sphere"):
        validate(s.replace(lights=tr.SphereLight()))
    for _ in range(2):  # the second time the rest of the scene is remembered
        with pytest.raises(ConfigError, match=r"camera: expected a torchrefract\.Camera"):
            validate(s.replace(camera=None))


def test_build_gbuffer_rejects_mismatched_cameras(tmp_path):
    from torchrefract.geometry.gbuffer import build_gbuffer
    from torchrefract.geometry.mesh import load_mesh

    s = load_scene(write(tmp_path, base(tmp_path)))
    m = load_mesh(s.mesh, s.transform)
    with pytest.raises(ValueError, match="samples_per_pixel"):
        build_gbuffer([m, m], [tr.Camera(width=8, height=8),
                               tr.Camera(width=8, height=8, samples_per_pixel=2)])
