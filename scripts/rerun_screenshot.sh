#!/usr/bin/env bash
# A screenshot of the Rerun viewer on a recording, on a machine without a display or GPU (how
# docs/images/rerun_kitti06.jpg was made): a virtual X server (Xvfb) and Mesa's software Vulkan driver (lavapipe);
# Rerun's OpenGL backend does not work there (it needs R32Float render targets).
#
#   scripts/rerun_screenshot.sh OUT/run.rrd shot.png [1600x900]
set -euo pipefail
if [[ $# -lt 2 ]]; then
    echo "usage: $0 RUN.rrd OUT.png [WIDTHxHEIGHT]" >&2
    exit 2
fi
command -v Xvfb >/dev/null || { echo "$0: Xvfb is not installed (apt-get install xvfb)" >&2; exit 1; }
command -v rerun >/dev/null || { echo "$0: the rerun viewer is not installed (pip install -e \".[viewer]\")" >&2; exit 1; }
DISPLAY_NUM=:${DISPLAY_NUM:-99}
Xvfb "$DISPLAY_NUM" -screen 0 1920x1200x24 >/dev/null 2>&1 &
XVFB=$!
trap 'kill $XVFB' EXIT
sleep 1
mkdir -p "${XDG_RUNTIME_DIR:=$(mktemp -d)}"
DISPLAY=$DISPLAY_NUM WGPU_BACKEND=vulkan XDG_RUNTIME_DIR=$XDG_RUNTIME_DIR \
    rerun --port auto --window-size "${3:-1600x900}" --screenshot-to "$2" "$1"
echo "wrote $2"
