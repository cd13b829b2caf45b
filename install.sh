#!/usr/bin/env bash
# Installs everything the editor and its tests need into ./.venv (Debian 12, Python 3.11, as root).
# System packages: Xvfb for GUI tests and headless use, Mesa for OpenGL (EGL/GLX), a C compiler for the
# native CPU kernels (core/field/csrc, core/render/csrc) and torch.compile.
set -euo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3.11}
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  need=""
  for p in xvfb xauth libegl1 libegl-mesa0 libgl1-mesa-dri libglx-mesa0 gcc g++ libc6-dev; do
    dpkg -s "$p" >/dev/null 2>&1 || need="$need $p"
  done
  if [ -n "$need" ]; then
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $need >/dev/null
  fi
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
# torch first, pinned to the CPU build; the project's own range is satisfied by it, so nothing larger is pulled.
.venv/bin/python -c "import torch" 2>/dev/null || .venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -e ".[all,test]"
echo "installed: $(.venv/bin/repaint-nerf --version)"
