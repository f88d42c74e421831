"""RenderSettings instead of process-wide switches: importing torchrefract and rendering
with the default settings leave the host process as it was (threads, umask, environment,
allocator); settings hold for one call; the old switches are deprecated aliases."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch
from conftest import ASSETS

import torchrefract as tr
from torchrefract.checks import ConfigError
from torchrefract.settings import RenderSettings, current, using

_PROBE = r"""
import os, resource, sys
import torch

def state():
    umask = [l.split()[1] for l in open("/proc/self/status") if l.startswith("Umask")][0]
    env = {k: v for k, v in os.environ.items() if k.startswith("TORCHREFRACT")}
    return torch.get_num_threads(), umask, env

def faults():  # page faults of 64 MB blocks, above glibc's largest dynamic mmap threshold
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(6):
        y = torch.ones(16_000_000)
        del y
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

torch.set_num_threads(1)
s0, f0 = state(), faults()
import torchrefract as tr
from torchrefract import heap
s1 = state()
scene = tr.Scene(mesh=sys.argv[1], envmap=tr.EnvMap(path=sys.argv[2]),
                 camera=tr.Camera(width=24, height=24), method="rousiers")
tr.render(scene)
s2, f2 = state(), faults()
print(s0 == s1 == s2, heap.heap_reuse(), f0, f2, s0, s2)
"""


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="reads /proc")
def test_import_and_default_render_change_no_process_state():
    env = {k: v for k, v in os.environ.items() if not k.startswith("TORCHREFRACT")}
    r = subprocess.run([sys.executable, "-c", _PROBE, str(ASSETS / "meshes" / "sphere.ply"),
                        str(ASSETS / "envmaps" / "studio_small_03.exr")],
                       capture_output=True, text=True, timeout=180, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    same, reuse, f0, f2 = r.stdout.split()[:4]
    assert same == "True", r.stdout
    assert reuse == "False"
    # the allocator still returns 64 MB blocks to the system: each one faults in again
    assert int(f2) >= 0.5 * int(f0) > 0, r.stdout


def test_settings_hold_for_one_call_and_threads_are_restored():
    threads = torch.get_num_threads()
    with using(RenderSettings(threads=1, native=False)) as s:
        assert current() is s and torch.get_num_threads() == 1
        assert not tr.RenderSettings().native or not current().native
    assert torch.get_num_threads() == threads
    assert current().native == RenderSettings.from_env().native


def test_settings_reach_the_render(monkeypatch):
    seen = []
    from torchrefract.kernels import native

    real = native.available
    monkeypatch.setattr(native, "available", lambda: seen.append(current()) or real())
    scene = tr.Scene(mesh=str(ASSETS / "meshes" / "sphere.ply"),
                     envmap=tr.EnvMap(path=str(ASSETS / "envmaps" / "studio_small_03.exr")),
                     camera=tr.Camera(width=16, height=16), method="specular")
    s = RenderSettings(native=False)
    tr.render(scene, settings=s)
    assert seen and all(x is s for x in seen)


def test_environment_variables_are_the_documented_defaults(monkeypatch):
    monkeypatch.setenv("TORCHREFRACT_NATIVE", "0")
    monkeypatch.setenv("TORCHREFRACT_COMPILE", "1")
    monkeypatch.setenv("TORCHREFRACT_THREADS", "3")
    monkeypatch.setenv("TORCHREFRACT_CACHE", "/tmp/x")
    s = RenderSettings.from_env()
    assert (s.native, s.compile, s.threads, s.cache_dir) == (False, True, 3, "/tmp/x")
    assert RenderSettings() == RenderSettings(threads=None, native=True, compile=False,
                                              heap_reuse=False)


def test_settings_made_in_code_keep_the_environments_cache_folder(monkeypatch, tmp_path):
    """TORCHREFRACT_CACHE moves the caches for every render of the process, also those
    given settings made in code for another field (else two renders of one process read
    tables and pyramids from two folders); an explicit cache_dir still wins."""
    from torchrefract.settings import cache_folder

    monkeypatch.setenv("TORCHREFRACT_CACHE", str(tmp_path / "env"))
    assert cache_folder(RenderSettings(threads=1)) == tmp_path / "env"
    assert cache_folder(RenderSettings.from_env()) == tmp_path / "env"
    assert cache_folder(RenderSettings(cache_dir=str(tmp_path / "own"))) == tmp_path / "own"
    monkeypatch.delenv("TORCHREFRACT_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_folder(RenderSettings()) == tmp_path / "xdg" / "torchrefract"


def test_bad_settings_are_named(monkeypatch):
    with pytest.raises(ConfigError, match="RenderSettings.threads"):
        RenderSettings(threads=0)
    with pytest.raises(ConfigError, match="RenderSettings.threads"):
        RenderSettings(threads=10 ** 30)  # (a C int in torch)
    for field in ("native", "fused", "adaptive", "heap_reuse"):  # "no" used to mean True
        with pytest.raises(ConfigError, match=f"RenderSettings.{field}: expected True or"):
            RenderSettings(**{field: "no"})
    with pytest.raises(ConfigError, match="RenderSettings.cache_dir"):
        RenderSettings(cache_dir=123)
    for var, value in (("TORCHREFRACT_THREADS", "abc"), ("TORCHREFRACT_MEMORY_MB", "64MB"),
                       ("TORCHREFRACT_NATIVE", "maybe")):
        monkeypatch.setenv(var, value)
        with pytest.raises(ConfigError, match=f"{var}='{value}'"):
            RenderSettings.from_env()
        monkeypatch.delenv(var)
    with pytest.raises(ConfigError, match="RenderSettings"):
        with using({"threads": 1}):  # type: ignore[arg-type]
            pass


def test_old_switches_are_deprecated_aliases(monkeypatch):
    # Registered with monkeypatch first (set, then deleted), so that its teardown ends with
    # the variables as they were: set_native / set_compile write os.environ themselves, and
    # a bare delenv at the end would be undone to their values (every later test then ran
    # with native kernels off and compilation on).
    for name in ("TORCHREFRACT_NATIVE", "TORCHREFRACT_COMPILE"):
        monkeypatch.setenv(name, "")
        monkeypatch.delenv(name)
    with pytest.warns(DeprecationWarning, match="RenderSettings"):
        tr.set_native(False)
    assert current().native is False
    with pytest.warns(DeprecationWarning, match="RenderSettings"):
        tr.set_compile(True)
    assert current().compile is True
    monkeypatch.delenv("TORCHREFRACT_NATIVE")
    monkeypatch.delenv("TORCHREFRACT_COMPILE")
    assert current().native and not current().compile


@pytest.mark.parametrize("flag, env, field, default", [
    ("--no-fused", "TORCHREFRACT_FUSED=0", "fused", True),
    ("--no-adaptive", "TORCHREFRACT_ADAPTIVE=0", "adaptive", True)])
def test_flag_and_environment_are_settings_of_the_run(monkeypatch, flag, env, field, default):
    """A command's flag (render and sweep) and its environment variable set the run's
    settings, not the process's; the Python API's default is ``default``."""
    from torchrefract.cli import _parser, _settings

    name, value = env.split("=")
    monkeypatch.delenv(name, raising=False)
    for cmd in (["render", "x.yaml", "--out", "o"], ["sweep", "x.yaml", "--out", "o"]):
        assert getattr(_settings(_parser().parse_args(cmd)), field) is default
        assert getattr(_settings(_parser().parse_args(cmd + [flag])), field) is not default
    monkeypatch.setenv(name, value)
    assert getattr(RenderSettings.from_env(), field) is not default
    assert getattr(RenderSettings(), field) is default


def test_threads_adapt_to_cores_other_processes_keep_busy(monkeypatch):
    """threads None: a call under load takes only the free cores (at least 1) and gives
    torch's count back after; an explicit count or adapt_threads=False is kept."""
    from torchrefract import cpu_load

    n = torch.get_num_threads()
    cores = os.cpu_count() or 1
    monkeypatch.setattr(cpu_load, "busy_cores", lambda *a, **k: cores)  # every core taken
    monkeypatch.setattr(cpu_load._busy, "last", None)  # no reading from before the patch
    with using(RenderSettings()):
        assert torch.get_num_threads() == 1
        with using(RenderSettings()):  # a nested block keeps the outer count
            assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == n
    with using(RenderSettings(adapt_threads=False)):
        assert torch.get_num_threads() == n
    with using(RenderSettings(threads=2)):
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == n
    assert cpu_load.threads_for(4, cores=8, busy=2) == 4
    assert cpu_load.threads_for(4, cores=4, busy=1) == 3
    assert cpu_load.threads_for(2, cores=2, busy=5) == 1
    assert RenderSettings.from_env().adapt_threads
    monkeypatch.setenv("TORCHREFRACT_ADAPT_THREADS", "0")
    assert not RenderSettings.from_env().adapt_threads


def test_load_is_read_at_most_once_a_second(monkeypatch):
    """Renders in quick succession share one reading of /proc; an old one is read anew."""
    from torchrefract import cpu_load

    calls = []
    monkeypatch.setattr(cpu_load, "busy_cores", lambda *a, **k: calls.append(1) or 0)
    monkeypatch.setattr(cpu_load._busy, "last", None)
    for _ in range(3):
        cpu_load.threads_for(2, cores=2)
    assert len(calls) == 1
    monkeypatch.setattr(cpu_load._busy, "last",
                        (cpu_load._busy.last[0] - 2 * cpu_load.MAX_AGE_S, 0))
    cpu_load.threads_for(2, cores=2)
    assert len(calls) == 2


def test_busy_cores_sees_a_busy_process():
    """A process spinning on a core is counted (the machine's other load may add more)."""
    import time

    from torchrefract.cpu_load import busy_cores

    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)
        assert max(busy_cores() for _ in range(5)) >= 1
    finally:
        hog.kill()
        hog.wait()
