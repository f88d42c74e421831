"""The package's layout by stage keeps its public names: the top-level API, the dataset
names in ``torchrefract.dataset``, and the old ``torchrefract.data`` module as a deprecated
alias."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

import torchrefract as tr


def test_top_level_api():
    for name in ("Camera", "ConfigError", "EnvMap", "Material", "RenderResult",
                 "RenderSettings", "Scene", "SphereLight", "Transform", "load_scene",
                 "register_method", "render", "scene_from_dict", "set_compile",
                 "set_heap_reuse", "set_native", "__version__"):
        assert hasattr(tr, name), name


def test_dataset_names_are_imported_when_used():
    code = ("import sys, torchrefract.dataset as d; assert 'torchrefract.dataset.loaders' "
            "not in sys.modules; d.RefractDataset; assert 'torchrefract.dataset.loaders' in "
            "sys.modules; print(d.run_sweep.__module__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "torchrefract.dataset.run", r.stderr
    import torchrefract.dataset as d

    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        d.nothing  # noqa: B018


def test_old_data_module_is_a_deprecated_alias():
    sys.modules.pop("torchrefract.data", None)
    with pytest.warns(DeprecationWarning, match="torchrefract.dataset"):
        data = importlib.import_module("torchrefract.data")
    from torchrefract.dataset import RefractDataset, RenderStream

    assert data.RefractDataset is RefractDataset and data.RenderStream is RenderStream
