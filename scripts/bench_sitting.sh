#!/usr/bin/env bash
# One bench sitting for issue #28's figures (docs/benchmarks.md, "Fused shading"): the
# fused kernels against Mitsuba and against the tensor code, the Python API's defaults,
# one thread, under load (a busy loop on one core), cold and warm start. ~5 min on 2 cores;
# run it with the machine otherwise quiet. Output: stdout, and outputs/bench_sitting/*/.
set -uo pipefail
cd "$(dirname "$0")/.."
mkdir -p outputs/bench_sitting
B=".venv/bin/python scripts/bench.py"
echo "== machine"; nproc; grep -m1 "model name" /proc/cpuinfo; date -u
echo "== A fused, 256+512 b8, with Mitsuba, interleaved (every row once per round)"
$B --methods specular prefiltered rousiers rousiers:internal_bounces=2 lean gsr --sizes 256 512 --batches 8 --repeats 5 --interleave --out outputs/bench_sitting/A 2>&1 | grep -v "saved\|^round"
echo "== B tensor code (--no-fused), 256 b8"
$B --methods specular prefiltered rousiers rousiers:internal_bounces=2 --sizes 256 --batches 8 --repeats 5 --no-fused --no-mitsuba --out outputs/bench_sitting/B 2>&1 | grep -v saved
echo "== C API defaults (--no-heap-reuse), 256 b8"
$B --methods specular prefiltered rousiers --sizes 256 --batches 8 --repeats 5 --no-heap-reuse --no-mitsuba --out outputs/bench_sitting/C 2>&1 | grep -v saved
echo "== D 1 thread, 256 b8"
$B --methods specular rousiers rousiers:internal_bounces=2 --sizes 256 --batches 8 --repeats 5 --threads 1 --no-mitsuba --out outputs/bench_sitting/D 2>&1 | grep -v saved
echo "== E under load (one core busy): default (threads adapt), 2 threads fixed, 1 thread"
( timeout 180 python3 -c "while True: pass" ) & HOG=$!
sleep 1
$B --methods specular rousiers --sizes 256 --batches 8 --repeats 5 --no-mitsuba --out outputs/bench_sitting/E2 2>&1 | grep -v saved
TORCHREFRACT_ADAPT_THREADS=0 $B --methods specular rousiers --sizes 256 --batches 8 --repeats 5 --no-mitsuba --out outputs/bench_sitting/E2f 2>&1 | grep -v saved
$B --methods specular rousiers --sizes 256 --batches 8 --repeats 5 --threads 1 --no-mitsuba --out outputs/bench_sitting/E1 2>&1 | grep -v saved
$B --methods rousiers --sizes 256 --batches 8 --repeats 5 --no-fused --no-mitsuba --out outputs/bench_sitting/E3 2>&1 | grep -v saved
kill $HOG 2>/dev/null; wait $HOG 2>/dev/null
echo "== F cold start (empty cache dir) and warm start: first frame of a new process"
rm -rf outputs/bench_sitting/cold
for kind in cold warm; do
  TIMEFORMAT="$kind: %R s wall"
  time .venv/bin/python -c "
import time; t0 = time.perf_counter()
import torchrefract as tr
s = tr.load_scene('configs/demo.yaml')
out = tr.render(s, settings=tr.RenderSettings(cache_dir='outputs/bench_sitting/cold'))
print('first frame after', round(time.perf_counter() - t0, 2), 's in-process', out.timings.get('fused', 0) > 0)
" 2>&1 | grep -v "^\[sgenv\]" | tail -2
done
echo "== done"; date -u
