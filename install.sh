#!/usr/bin/env bash
# Installs everything the editor and its tests need into ./.venv (Debian 12, Python 3.11, as root).
# System packages: Xvfb for GUI tests and headless use, Mesa for OpenGL (EGL/GLX), a C compiler for the
# native CPU kernels (core/field/csrc, core/render/csrc) and torch.compile.
# One line per phase on the terminal; what apt and pip print goes to install.log, shown when a phase fails.
set -Eeuo pipefail
cd "$(dirname "$0")"
PY=${PYTHON:-python3.11}
LOG="$PWD/install.log"
: >"$LOG"
PHASE="start"
trap 'rc=$?; echo "failed"; echo "install.sh: the \"$PHASE\" phase failed (exit $rc). Its last lines (all of it: $LOG):" >&2
      tail -n 30 "$LOG" >&2; exit $rc' ERR

phase() { PHASE=$1; printf '%-17s' "$1:"; }
quiet() { echo "+ $*" >>"$LOG"; "$@" >>"$LOG" 2>&1; }

phase "system packages"
if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
  need=""
  for p in xvfb xauth libegl1 libegl-mesa0 libgl1-mesa-dri libglx-mesa0 gcc g++ libc6-dev; do
    dpkg -s "$p" >/dev/null 2>&1 || need="$need $p"
  done
  if [ -n "$need" ]; then
    quiet apt-get update -qq
    DEBIAN_FRONTEND=noninteractive quiet apt-get install -y -qq $need
    echo "installed$need"
  else
    echo "already present (Xvfb, Mesa OpenGL, gcc)"
  fi
else
  echo "skipped (needs apt-get and root; install Xvfb, Mesa's libEGL/libGL and gcc yourself)"
fi

phase "venv"
if [ -x .venv/bin/python ]; then kept=" (kept)"; else kept=""; quiet "$PY" -m venv .venv; fi
quiet .venv/bin/python -m pip install --upgrade pip
v=$(.venv/bin/python --version)
echo ".venv, $v$kept"

# torch first, pinned to the CPU build; the project's own range is satisfied by it, so nothing larger is pulled.
phase "torch"
if .venv/bin/python -c "import torch" >>"$LOG" 2>&1; then kept=" (kept)"; else kept=""; quiet .venv/bin/python -m pip install "torch==2.13.0"; fi
v=$(.venv/bin/python -W ignore -c 'import torch; print(torch.__version__)' 2>>"$LOG")
echo "$v$kept"

phase "package"
quiet .venv/bin/python -m pip install -e ".[all,test]"
v=$(.venv/bin/repaint-nerf --version 2>>"$LOG")
echo "$v with its extras (diffusion, lite, test)"
echo "done: .venv/bin/repaint-nerf opens the editor; the install's full output is in install.log"
