#!/usr/bin/env bash
# Set up everything perception_config needs, idempotently (a second run takes seconds):
#   1. system packages (apt) the stack needs, installed when missing;
#   2. a virtual environment in .venv with exactly the packages of requirements.lock (hash-checked;
#      ./scripts/lock.sh refreshes the lock from requirements.txt);
#   3. the package itself, with msg_defs/ compiled into perception_config_interfaces.
# Sourced by scripts/demo.sh and scripts/test.sh; can also be run on its own.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${PERCEPTION_CONFIG_VENV:-$ROOT/.venv}"
PY="$VENV/bin/python"

# This machine's pip config names local wheel folders that may be absent; keep pip's output readable.
quiet_pip() { "$PY" -m pip "$@" 2> >(grep -v "^WARNING: Location 'file://" >&2); }
say() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }
die() { printf '\033[1;31m[setup] error:\033[0m %s\n' "$*" >&2; exit 1; }

# --- 1. Python 3.11 ------------------------------------------------------------------------
pick_python() {
  for c in "${PYTHON:-}" python3.11 python3; do
    [ -n "$c" ] || continue
    if command -v "$c" >/dev/null 2>&1 && "$c" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
      echo "$c"; return 0
    fi
  done
  return 1
}

# --- 2. System packages ----------------------------------------------------------------------
# name of the Debian package -> a check that succeeds when it is present
missing=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)   # open3d imports it
command -v cmake >/dev/null 2>&1 || missing+=(cmake)     # compiles msg_defs/
command -v ninja >/dev/null 2>&1 || command -v make >/dev/null 2>&1 || missing+=(ninja-build)
command -v cc >/dev/null 2>&1 || missing+=(gcc)
command -v c++ >/dev/null 2>&1 || missing+=(g++)
have_lib 'libGL.so.1' || missing+=(libgl1)               # open3d's visualization module links it
have_lib 'libgomp.so.1' || missing+=(libgomp1)
# Software OpenGL over EGL for bop_toolkit's VSD renderer (vispy; test/test_bop_toolkit.py, docs/how-to/bop_toolkit.md)
have_lib 'libEGL.so.1' || missing+=(libegl1)
have_lib 'libEGL_mesa.so.0' || missing+=(libegl-mesa0)
have_lib 'libOpenGL.so.0' || missing+=(libopengl0)
compgen -G '/usr/lib/*/dri/swrast_dri.so' >/dev/null || compgen -G '/usr/lib/*/dri/llvmpipe_dri.so' >/dev/null \
  || missing+=(libgl1-mesa-dri)
PYTHON_BIN="$(pick_python || true)"
if [ -z "$PYTHON_BIN" ]; then
  missing+=(python3 python3-venv python3-dev)
elif ! "$PYTHON_BIN" -c 'import venv, ensurepip' >/dev/null 2>&1; then
  missing+=(python3-venv)
fi
if [ -n "$PYTHON_BIN" ]; then
  inc="$("$PYTHON_BIN" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
  [ -f "$inc/Python.h" ] || missing+=(python3-dev)
fi

if [ ${#missing[@]} -gt 0 ]; then
  say "installing system packages: ${missing[*]}"
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then
    command -v sudo >/dev/null 2>&1 && SUDO="sudo" || die "missing system packages (${missing[*]}) and not root: install them with apt-get"
  fi
  command -v apt-get >/dev/null 2>&1 || die "missing system packages (${missing[*]}) and no apt-get: install them with your package manager"
  $SUDO apt-get update -qq || die "apt-get update failed"
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" \
    || die "apt-get install failed for: ${missing[*]}"
  PYTHON_BIN="$(pick_python || true)"
fi
[ -n "$PYTHON_BIN" ] || die "Python 3.11 is required (python3.11 not found after installing python3)"
cmake_version="$(cmake --version | head -n1 | grep -oE '[0-9]+\.[0-9]+' | head -n1)"
"$PYTHON_BIN" -c "import sys; v=tuple(map(int,'$cmake_version'.split('.'))); sys.exit(v < (3, 20))" \
  || die "cmake >= 3.20 is required to compile msg_defs/, found $cmake_version"

# --- 3. Virtual environment and requirements -------------------------------------------------
if [ ! -x "$PY" ] || ! "$PY" -c 'import sys' >/dev/null 2>&1; then
  say "creating virtual environment $VENV"
  rm -rf "$VENV"
  "$PYTHON_BIN" -m venv "$VENV"
fi
export PIP_DISABLE_PIP_VERSION_CHECK=1
# Two set-ups at once (two shells, or a test run beside a demo) take turns on the venv.
exec 9>"$VENV/.setup.lock"
flock 9

hash_of() { cat "$@" 2>/dev/null | sha256sum | cut -d' ' -f1; }
req_hash="$(hash_of "$ROOT/requirements.lock" "$ROOT/requirements.txt")"
if [ "$(cat "$VENV/.requirements.sha256" 2>/dev/null)" != "$req_hash" ]; then
  say "installing requirements.lock (first run: a few minutes)"
  # opencv-contrib-python-headless (cv2.linemod) replaces opencv-python-headless: both install cv2/,
  # so an older venv's plain wheel goes first (left in place, uninstalling either breaks the other).
  if "$PY" -m pip show -q opencv-python-headless >/dev/null 2>&1; then
    quiet_pip uninstall -q -y opencv-python-headless opencv-contrib-python-headless \
      || die "pip uninstall opencv-python-headless failed"
  fi
  # A new venv has the interpreter's bundled pip (23.2.1 with Python 3.11.7), which refuses the
  # hash-checked lock as soon as an index offers a release newer than the lock's of a dependency
  # that is required with an extra (pytest-cov's coverage[toml]); the lock's own pip goes first.
  want_pip="$(sed -n 's/^pip==\([^ ]*\).*/\1/p' "$ROOT/requirements.lock")"
  if [ -n "$want_pip" ] && [ "$("$PY" -m pip --version | cut -d' ' -f2)" != "$want_pip" ]; then
    say "installing pip $want_pip (the lock's, hash-checked) first"
    pip_req="$(mktemp)"
    awk '/^pip==/ {on = 1} on {print} on && !/\\$/ {exit}' "$ROOT/requirements.lock" > "$pip_req"
    quiet_pip install -q --require-hashes -r "$pip_req" || { rm -f "$pip_req"; die "installing pip $want_pip failed"; }
    rm -f "$pip_req"
  fi
  # Exact versions, every file's sha256 checked; torch==2.13.0+cpu comes from pip's find-links folder.
  quiet_pip install -q --require-hashes -r "$ROOT/requirements.lock" || die "pip install -r requirements.lock failed"
  # A line added to requirements.txt without ./scripts/lock.sh still gets installed (unhashed);
  # test/test_packaging.py fails until the lock is refreshed. A no-op when the lock covers everything.
  quiet_pip install -q -r "$ROOT/requirements.txt" || die "pip install -r requirements.txt failed"
  echo "$req_hash" > "$VENV/.requirements.sha256"
fi

# --- 4. The package with its compiled interfaces ---------------------------------------------
src_files=$(cd "$ROOT" && find setup.py setup.cfg package.xml msg_defs perception_config resource \
  -type f \( -name '*.py' -o -name '*.msg' -o -name '*.srv' -o -name '*.txt' -o -name '*.xml' \
  -o -name '*.yaml' -o -name '*.cfg' -o -name 'perception_config' \) -not -path '*/__pycache__/*' | sort)
pkg_hash="$(cd "$ROOT" && hash_of $src_files)"
if [ "$(cat "$VENV/.package.sha256" 2>/dev/null)" != "$pkg_hash" ] \
   || ! "$PY" -c 'import perception_config_interfaces.srv' >/dev/null 2>&1; then
  say "installing perception_config and compiling msg_defs/"
  (cd "$ROOT" && quiet_pip install -q --no-build-isolation --no-deps . ) \
    || die "installing perception_config failed (see the build output above)"
  "$PY" -c 'import perception_config_interfaces.msg, perception_config_interfaces.srv' \
    || die "perception_config_interfaces does not import after the install"
  echo "$pkg_hash" > "$VENV/.package.sha256"
fi
# Bytecode of the checkout, written once: with PYTHONDONTWRITEBYTECODE set (as in some shells and
# CI images) Python never caches it, so every process importing the package from the checkout (the
# tests and the processes they start) would compile its ~200 modules again. Reading it stays allowed.
"$PY" -m compileall -q -j 0 "$ROOT/perception_config" "$ROOT/test" >/dev/null || say "compileall failed (harmless)"
flock -u 9
exec 9>&-
export PATH="$VENV/bin:$PATH"
