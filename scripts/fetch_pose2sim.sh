#!/usr/bin/env bash
# Fetch the real Qualisys demo recordings shipped in the pose2sim==0.10.49 wheel
# (BSD-3-Clause; see /work/shared/DATA.md). Used as data only.
#
# Downloads the wheel (no dependencies) into the cache directory and unzips only
#   Pose2Sim/Demo_SinglePerson/videos/       cam01..04.mp4 (one man)
#   Pose2Sim/Demo_SinglePerson/calibration/  Calib.qca.txt
#   Pose2Sim/Demo_MultiPerson/videos/        cam01..04.mp4 (the man and a woman; same calibration)
#   Pose2Sim/Demo_MultiPerson/calibration/
# Idempotent: every step is skipped when its result is already there.
#
# Usage: scripts/fetch_pose2sim.sh            (cache: ${ARTRACK_CACHE:-<repo>/.cache})
# Result: $CACHE/pose2sim/Pose2Sim/Demo_{SinglePerson,MultiPerson}/{videos,calibration}
set -euo pipefail
if [ "${1:-}" = "-h" ] || [ "${1:-}" = "--help" ]; then
  sed -n '2,/^[^#]/{/^#/s/^# \{0,1\}//p}' "$0"  # the comment block above
  exit 0
fi
if [ $# -gt 0 ]; then echo "fetch_pose2sim: unknown argument '$1' (see --help)" >&2; exit 2; fi
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
CACHE=${ARTRACK_CACHE:-$ROOT/.cache}
VERSION=0.10.49
WHEEL_DIR=$CACHE/wheels
DEST=$CACHE/pose2sim
DEMOS=(Pose2Sim/Demo_SinglePerson Pose2Sim/Demo_MultiPerson)
PY=$ROOT/.venv/bin/python
[ -x "$PY" ] || PY=python3

mkdir -p "$WHEEL_DIR" "$DEST"

have_all=1
for DEMO in "${DEMOS[@]}"; do
  if ! [ -f "$DEST/$DEMO/calibration/Calib.qca.txt" ] || \
     [ "$(find "$DEST/$DEMO/videos" -name '*.mp4' 2>/dev/null | wc -l)" -lt 4 ]; then
    have_all=0
  fi
done
if [ "$have_all" = 1 ]; then
  echo "fetch_pose2sim: already present in $DEST/Pose2Sim"
  exit 0
fi

WHEEL=$(find "$WHEEL_DIR" -maxdepth 1 -name "pose2sim-$VERSION-*.whl" | head -n 1)
if [ -z "$WHEEL" ]; then
  echo "fetch_pose2sim: downloading pose2sim==$VERSION into $WHEEL_DIR"
  "$PY" -m pip download --no-deps --disable-pip-version-check -q -d "$WHEEL_DIR" "pose2sim==$VERSION"
  WHEEL=$(find "$WHEEL_DIR" -maxdepth 1 -name "pose2sim-$VERSION-*.whl" | head -n 1)
  [ -n "$WHEEL" ] || { echo "fetch_pose2sim: download produced no wheel in $WHEEL_DIR" >&2; exit 1; }
fi

echo "fetch_pose2sim: extracting ${DEMOS[*]} {videos,calibration} from $(basename "$WHEEL")"
# Extract into a temp dir, then move into place, so an interrupted run leaves nothing half-done.
TMP=$(mktemp -d "$DEST/.extract.XXXXXX")
trap 'rm -rf "$TMP"' EXIT
"$PY" - "$WHEEL" "$TMP" "${DEMOS[@]}" <<'PYEOF'
import sys, zipfile
wheel, out, demos = sys.argv[1], sys.argv[2], sys.argv[3:]
prefixes = tuple(f"{d}/{sub}/" for d in demos for sub in ("videos", "calibration"))
with zipfile.ZipFile(wheel) as z:
    names = [n for n in z.namelist() if n.startswith(prefixes) and not n.endswith("/")]
    for d in demos:
        if not any(n.startswith(f"{d}/videos/") for n in names):
            sys.exit(f"fetch_pose2sim: {wheel} holds no {d}/videos/")
    for n in names:
        z.extract(n, out)
    print(f"fetch_pose2sim: {len(names)} files")
PYEOF
for DEMO in "${DEMOS[@]}"; do
  for sub in videos calibration; do
    mkdir -p "$DEST/$DEMO"
    [ -d "$TMP/$DEMO/$sub" ] || continue
    rm -rf "$DEST/$DEMO/$sub"
    mv "$TMP/$DEMO/$sub" "$DEST/$DEMO/$sub"
  done
done
echo "fetch_pose2sim: done -> $DEST/Pose2Sim"
