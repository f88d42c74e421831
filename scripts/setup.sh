#!/usr/bin/env bash
# One-time (and idempotent) set-up: Debian GL libraries, a virtual environment in .venv,
# the torch CPU wheel, then torchrefract with its extras. Safe to run again: it only
# installs what is missing. Usage: bash scripts/setup.sh [extras]   (default extras: test)
set -euo pipefail
cd "$(dirname "$0")/.."
EXTRAS="${1:-test}"
PY="${PYTHON:-python3.11}"
command -v "$PY" >/dev/null 2>&1 || PY=python3

say() { echo "[setup] $*"; }

# 1. Debian libraries for headless OpenGL (EGL on Mesa) and the C compiler of the native
#    and fused kernels (torchrefract/kernels/native.py), only when missing.
need_apt=()
for pkg in libegl1 libegl-mesa0 libgl1; do
  dpkg -s "$pkg" >/dev/null 2>&1 || need_apt+=("$pkg")
done
want_cc=0  # optional: without a compiler the tensor code runs (same images, slower)
command -v cc >/dev/null 2>&1 || command -v gcc >/dev/null 2>&1 || want_cc=1
# Mitsuba's fast LLVM variant needs libLLVM 19 (Mesa's libLLVM 15 crashes it); optional.
want_llvm=0
if [[ "$EXTRAS" == *test* || "$EXTRAS" == *reference* ]] && ! dpkg -s libllvm19 >/dev/null 2>&1; then
  want_llvm=1
fi
if (( ${#need_apt[@]} )) || (( want_llvm )) || (( want_cc )); then
  SUDO=""
  [[ $(id -u) -ne 0 ]] && command -v sudo >/dev/null 2>&1 && SUDO="sudo"
  if command -v apt-get >/dev/null 2>&1 && { [[ $(id -u) -eq 0 ]] || [[ -n "$SUDO" ]]; }; then
    say "apt-get install ${need_apt[*]} $( ((want_llvm)) && echo libllvm19 ) $( ((want_cc)) && echo gcc )"
    $SUDO apt-get update -qq >/dev/null
    if (( ${#need_apt[@]} )); then
      DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}" >/dev/null
    fi
    if (( want_cc )); then
      DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq gcc libc6-dev >/dev/null \
        || say "gcc not available: the tensor code runs instead of the native kernels"
    fi
    if (( want_llvm )); then
      DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null \
        || say "libllvm19 not available: Mitsuba will use its slower scalar_rgb variant"
    fi
  elif (( ${#need_apt[@]} )); then
    say "missing Debian packages ${need_apt[*]} and no apt-get/root to install them" >&2
    exit 1
  fi
fi

# 2. Virtual environment.
if [[ ! -x .venv/bin/python ]]; then
  say "creating .venv with $($PY --version)"
  "$PY" -m venv .venv
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null
fi
PIP=(.venv/bin/python -m pip install -q --disable-pip-version-check)

# 3. The torch CPU wheel first (a bare 'torch' would pull a multi-GB CUDA build).
if ! .venv/bin/python -c "import torch" >/dev/null 2>&1; then
  say "installing torch==2.13.0 (CPU wheel)"
  "${PIP[@]}" torch==2.13.0
fi

# 4. The package and its extras, re-installed only when pyproject.toml or the extras change.
stamp=".venv/.torchrefract-installed"
want="$(sha256sum pyproject.toml | cut -d' ' -f1) $EXTRAS"
if [[ ! -f "$stamp" ]] || [[ "$(cat "$stamp")" != "$want" ]]; then
  say "installing torchrefract[$EXTRAS]"
  "${PIP[@]}" -e ".[$EXTRAS]"
  echo "$want" > "$stamp"
fi
# 5. The native kernels (torchrefract/kernels/native.py: march, G-buffer), built now, not in the first
#    render; without a C compiler the renders use the tensor code (same images).
.venv/bin/python -c "import torchrefract.kernels.native as n; n.build()" >/dev/null 2>&1 \
  || say "note: the native kernels did not build (no C compiler?); the tensor code runs instead"
say "ready: $(.venv/bin/python -c 'import torch, torchrefract; print("torchrefract", torchrefract.__version__, "torch", torch.__version__)')"
