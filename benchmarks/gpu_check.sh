#!/usr/bin/env bash
# GPU check of issue 15 on one CUDA machine without network, well within 8 minutes on one H200:
#   bash benchmarks/gpu_check.sh [ARGS]     ARGS go to benchmarks/gpu_check.py (e.g. --device cpu --quick)
# It runs benchmarks/gpu_check.py (batched inference on KITTI 06 at batch 16 and 64 with FPS and ms per stage, one
# depth and one flow training step at 640x192 with it/s and memory, CPU-vs-GPU trajectory agreement) and writes
# ${OUT:-outputs/gpu_check}/gpu_check.json (also printed). Exit status: that of gpu_check.py (1: a section failed).
#
# Python: a virtual environment in ${GPU_CHECK_VENV:-/tmp/dfvo-gpu-venv} that sees the machine's own packages
# (--system-site-packages), so the machine's CUDA build of torch is used when it has one; whatever else is missing
# is installed from the wheel folder .whl/ at the repository root, with no index (no network). GPU_CHECK_VENV=none
# uses ${PYTHON:-python3} as it is.
#
# Building .whl/ (on a machine with network, the same Python minor version and platform as the GPU machine):
#   bash benchmarks/gpu_check.sh --build-wheels
# runs `pip wheel` for the project's runtime dependencies into .whl/ (pure-Python sdists such as antlr4 are built into
# wheels) and removes the torch and nvidia-* wheels (the CPU machine has no CUDA torch to give; the GPU machine's own
# torch is used). To bring a CUDA torch along instead:
#   pip download --dest .whl --no-deps torch==2.13.0 --index-url https://download.pytorch.org/whl/cu128
# (plus its nvidia-* wheels without --no-deps). The GPU machine needs only what it lacks: drop wheels it already has
# to keep the folder small. KITTI 06 (the 51-frame snippet) travels too when packed into an ignored folder:
#   bash benchmarks/gpu_check.sh --pack-kitti [../shared/data/kitti_odom]     -> outputs/gpu_check/kitti_odom
# Without it (and without DFVO_KITTI_ODOM_ROOT or ../shared/data/kitti_odom) the check uses the synthetic drive.
set -euo pipefail
REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO"
WHL="$REPO/.whl"
PACKED="$REPO/outputs/gpu_check/kitti_odom"
OUT_DIR="${OUT:-$REPO/outputs/gpu_check}"
PY="${PYTHON:-python3}"
DEPS=("kornia>=0.8" "numpy>=1.26" "lightning>=2.4" "hydra-core>=1.3" "tensorboard>=2.15" "matplotlib>=3.8"
      "pillow>=10" "safetensors>=0.4" "hydra-joblib-launcher>=1.2" "tqdm")
MODULES=(kornia numpy lightning hydra tensorboard matplotlib PIL safetensors hydra_plugins.hydra_joblib_launcher tqdm)

if [[ "${1:-}" == "--build-wheels" ]]; then
  mkdir -p "$WHL"
  "$PY" -m pip wheel --wheel-dir "$WHL" "${DEPS[@]}"
  rm -f "$WHL"/torch-*.whl "$WHL"/nvidia_*.whl "$WHL"/triton-*.whl
  du -sh "$WHL"
  exit 0
fi
if [[ "${1:-}" == "--pack-kitti" ]]; then
  src="${2:-$REPO/../shared/data/kitti_odom}"
  mkdir -p "$PACKED/sequences/06" "$PACKED/poses"
  cp -r "$src/sequences/06/image_0" "$src/sequences/06/calib.txt" "$PACKED/sequences/06/"
  [[ -f "$src/sequences/06/times.txt" ]] && cp "$src/sequences/06/times.txt" "$PACKED/sequences/06/"
  cp "$src/poses/06.txt" "$PACKED/poses/"
  du -sh "$PACKED"
  exit 0
fi

start=$(date +%s)
if [[ "${GPU_CHECK_VENV:-}" != "none" ]]; then
  venv="${GPU_CHECK_VENV:-/tmp/dfvo-gpu-venv}"
  [[ -x "$venv/bin/python" ]] || "$PY" -m venv --system-site-packages "$venv"
  PY="$venv/bin/python"
fi
if ! "$PY" -c "import torch" 2>/dev/null; then
  if ! ls "$WHL"/torch-*.whl >/dev/null 2>&1; then
    echo "gpu_check: this machine has no torch and $WHL has no torch wheel (see the header of $0)" >&2
    exit 2
  fi
  "$PY" -m pip install --no-index --find-links "$WHL" torch
fi
missing=()
for i in "${!MODULES[@]}"; do
  "$PY" -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('${MODULES[$i]}') is None)" 2>/dev/null \
    || missing+=("${DEPS[$i]}")
done
if (( ${#missing[@]} )); then
  echo "gpu_check: installing from $WHL: ${missing[*]}"
  "$PY" -m pip install --no-index --find-links "$WHL" "${missing[@]}"
fi
"$PY" -c "import torch; print('gpu_check: torch', torch.__version__, 'cuda', torch.cuda.is_available())"
echo "gpu_check: environment ready after $(( $(date +%s) - start )) s"

kitti="${DFVO_KITTI_ODOM_ROOT:-}"
[[ -z "$kitti" && -d "$PACKED/sequences/06" ]] && kitti="$PACKED"
[[ -z "$kitti" ]] && kitti="$REPO/../shared/data/kitti_odom"
mkdir -p "$OUT_DIR"
# 8 minutes in all: the check itself gets what the set-up left, less a margin
budget=$(( ${GPU_CHECK_BUDGET_S:-480} - ($(date +%s) - start) - 20 ))
status=0
timeout "$budget" "$PY" -m benchmarks.gpu_check --kitti-root "$kitti" --out "$OUT_DIR/gpu_check.json" "$@" || status=$?
[[ $status -eq 124 ]] && echo "gpu_check: stopped after ${budget} s; $OUT_DIR/gpu_check.json holds the finished sections" >&2
exit $status
