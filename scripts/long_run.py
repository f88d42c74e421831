"""Long-run memory check (issue #27, "runs that hold"): render a long sweep with the
``torchrefract sweep`` command and record its resident memory against the samples written.

    .venv/bin/python scripts/long_run.py --samples 5000 --out outputs/long_run

Writes ``OUT/dataset/`` (the sweep), ``OUT/memory.csv`` (seconds, samples written, RSS MB
of the sweep process and its children) and ``OUT/memory.json`` (the slope of RSS against
samples while they are rendered, after the first ``--skip`` samples and over the last 40%,
MB per 1,000 samples by least squares; the peak while rendering and at the run's close),
and prints them. The sweep: random samples at 128x128 of two meshes in random
poses under two maps, `rousiers`, one sample per pixel (``configs/sweep_throughput.yaml``'s
distribution at a smaller size).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent


def _config(n: int, size: int, path: Path) -> Path:
    cfg = yaml.safe_load((ROOT / "configs" / "sweep_throughput.yaml").read_text())
    cfg["name"] = "long_run"
    cfg["description"] = f"{n} random samples at {size}x{size} (scripts/long_run.py)"
    cfg["base"] = str(ROOT / "configs" / "demo.yaml")
    cfg["sampling"]["num_samples"] = n
    cfg["sweep"]["mesh"]["path"] = [str(ROOT / "assets" / "meshes" / m)
                                    for m in ("spot.ply", "suzanne.ply")]
    cfg["sweep"]["envmap"]["path"] = [str(ROOT / "assets" / "envmaps" / e)
                                      for e in ("studio_small_03.exr", "lebombo.exr")]
    cfg["sweep"]["camera"]["resolution"] = size
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def _rss_mb(pid: int) -> float:
    """Resident memory of ``pid`` and its children (MB); 0 once it is gone."""
    total = 0
    for p in [pid, *_children(pid)]:
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
        except OSError:
            pass
    return total / 1024


def _children(pid: int) -> list[int]:
    try:
        kids = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    except OSError:
        return []
    out = [int(k) for k in kids]
    return out + [g for k in out for g in _children(k)]


def _lines(path: Path) -> int:
    try:
        with open(path, "rb") as f:
            return f.read().count(b"\n")
    except OSError:
        return 0


def _slope(rows: list[tuple[float, int, float]], skip: int, end: int) -> float | None:
    """Least-squares slope of RSS (MB) against samples, per 1,000 samples, while samples
    ``skip`` .. ``end`` - 1 are rendered (not the run's close: its manifest compaction
    reads the whole manifest once)."""
    pts = [(n, m) for _, n, m in rows if skip <= n < end]
    if len(pts) < 3 or pts[-1][0] == pts[0][0]:
        return None
    mx = sum(n for n, _ in pts) / len(pts)
    my = sum(m for _, m in pts) / len(pts)
    sxx = sum((n - mx) ** 2 for n, _ in pts)
    sxy = sum((n - mx) * (m - my) for n, m in pts)
    return 1000.0 * sxy / sxx


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=5000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--skip", type=int, default=200, help="samples before the slope is fit")
    ap.add_argument("--out", default="outputs/long_run")
    ap.add_argument("--interval", type=float, default=0.5, help="seconds between readings")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = _config(args.samples, args.size, out / "long_run.yaml")
    data = out / "dataset"
    cmd = [sys.executable, "-m", "torchrefract.cli", "sweep", str(cfg), "--out", str(data),
           "--quiet"]
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd)
    rows: list[tuple[float, int, float]] = []
    with open(out / "memory.csv", "w") as csv:
        csv.write("seconds,samples,rss_mb\n")
        while proc.poll() is None:
            row = (time.monotonic() - t0, _lines(data / "manifest.jsonl"), _rss_mb(proc.pid))
            if row[2] > 0:
                rows.append(row)
                csv.write(f"{row[0]:.1f},{row[1]},{row[2]:.1f}\n")
                csv.flush()
            time.sleep(args.interval)
    slope = _slope(rows, args.skip, args.samples)
    last = _slope(rows, args.samples * 3 // 5, args.samples)
    rendering = [m for _, n, m in rows if n < args.samples]
    report = {"samples": args.samples, "size": args.size, "exit_code": proc.returncode,
              "seconds": round(time.monotonic() - t0, 1),
              "peak_rss_mb": round(max((m for _, _, m in rows), default=0.0), 1),
              "peak_rss_rendering_mb": round(max(rendering, default=0.0), 1),
              "rss_after_skip_mb": next((round(m, 1) for _, n, m in rows if n >= args.skip),
                                        None),
              "rss_end_mb": round(rows[-1][2], 1) if rows else None,
              "slope_mb_per_1000_samples": None if slope is None else round(slope, 3),
              "slope_last_40pct_mb_per_1000": None if last is None else round(last, 3),
              "readings": len(rows)}
    (out / "memory.json").write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    return proc.returncode


if __name__ == "__main__":
    raise SystemExit(main())
