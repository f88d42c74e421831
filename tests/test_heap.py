"""torchrefract.heap: freed tensor memory is reused instead of faulted in again (glibc's
mmap threshold), on where the settings ask (the CLI and its worker processes), off
otherwise."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from torchrefract import heap

glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's allocator only")


_FAULTS = """
import resource, torch
from torchrefract import heap

def faults(n=40):  # page faults of n ops that each allocate and free an 8 MB tensor
    x = torch.ones(2_000_000)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        y = x * 2.0
        del y
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

assert heap.set_heap_reuse(False)
fresh = faults()
assert heap.set_heap_reuse(True) and heap.heap_reuse()
faults(2)  # the heap grows once
print(fresh, faults())
"""


@glibc
def test_reuse_saves_the_page_faults_of_fresh_blocks():
    """In a fresh process (the suite's own heap is shaped by every test before)."""
    env = {k: v for k, v in os.environ.items() if k != "TORCHREFRACT_HEAP_REUSE"}
    r = subprocess.run([sys.executable, "-c", _FAULTS], capture_output=True, text=True,
                       env={**env, "OMP_NUM_THREADS": "1"}, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    fresh, reused = map(int, r.stdout.split())
    # 40 x 8 MB of fresh pages: ~78,000 faults of 4 KiB pages (measured), or a few of
    # 2 MiB ones where transparent huge pages back the blocks (each zeroing 2 MiB);
    # reused: none but noise, either way
    assert reused <= max(50, fresh // 20), (fresh, reused)


@glibc
def test_never_at_import_the_environment_is_the_settings_default_or_a_no():
    code = ("import torchrefract.heap as h, torchrefract as tr; a = h.heap_reuse(); "
            "from torchrefract.settings import using; "
            "s = tr.RenderSettings.from_env(); "
            "exec('with using(s): pass'); print(a, s.heap_reuse, h.heap_reuse())")
    run = lambda v: subprocess.run([sys.executable, "-c", code], capture_output=True,  # noqa: E731
                                   text=True, env={**os.environ, "TORCHREFRACT_HEAP_REUSE": v},
                                   timeout=120).stdout.split()
    assert run("1") == ["False", "True", "True"]  # asked for by the settings' default
    assert run("") == ["False", "False", "False"]  # off for the Python API
    assert run("0") == ["False", "False", "False"]


def test_the_cli_asks_for_it_in_its_settings(monkeypatch):
    """The command owns its process: its RenderSettings ask for heap reuse (handed to worker
    processes with each batch), unless ``TORCHREFRACT_HEAP_REUSE=0``; the environment is
    left as it is."""
    from torchrefract.cli import _parser, _settings

    args = _parser().parse_args(["render", "x.yaml", "--out", "o"])
    monkeypatch.delenv("TORCHREFRACT_HEAP_REUSE", raising=False)
    assert _settings(args).heap_reuse
    assert "TORCHREFRACT_HEAP_REUSE" not in os.environ
    monkeypatch.setenv("TORCHREFRACT_HEAP_REUSE", "0")  # the user's no is kept
    assert not _settings(args).heap_reuse
    was = heap.heap_reuse()
    try:
        heap.set_heap_reuse(False)
        assert not heap.set_heap_reuse(True) and not heap.heap_reuse()  # forbidden
    finally:
        monkeypatch.delenv("TORCHREFRACT_HEAP_REUSE")
        heap.set_heap_reuse(was)
