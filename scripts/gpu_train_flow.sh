#!/usr/bin/env bash
# The flow network on one H200-class GPU within 10 minutes: `python train.py experiment=flow_gpu trainer=gpu` (the
# synthetic worlds of every scenario rendered ON THE GPU into the render cache, supervised then mixed with
# self-supervised KITTI raw pairs; bf16-mixed, channels-last), stopped by TIME_LIMIT (SIGTERM: last.ckpt written,
# exit 143; run the script again to resume from it), then the held-out comparison of the result.
#
#   DFVO_KITTI_RAW_ROOT=../shared/data/kitti_raw scripts/gpu_train_flow.sh [RUNS_DIR]           # the GPU recipe
#   DFVO_KITTI_RAW_ROOT=../shared/data/kitti_raw scripts/gpu_train_flow.sh [RUNS_DIR] --quick   # CPU plumbing check
#
# NOT YET RUN on GPU hardware. Outputs RUNS_DIR/flow_gpu/ (default runs/): checkpoints/last.ckpt (resumable),
# weights.safetensors (infer.py flow.checkpoint=...), the Hydra log with one line per 100 steps and per validation
# (held-out AEPE per scenario). --quick: trainer=smoke at the smoke size (1 world, 3 steps, CPU), about a minute.
# The result is a candidate, not a shipped model: compare it with
#   python studies/flow_vs_classical.py --checkpoint RUNS_DIR/flow_gpu/weights.safetensors
# Environment: TIME_LIMIT (seconds of training, 540), TRAIN_CMD (default "python train.py").
set -euo pipefail
cd "$(dirname "$0")/.."
: "${DFVO_KITTI_RAW_ROOT:?set DFVO_KITTI_RAW_ROOT to the KITTI raw root (the folder holding 2011_09_26/...)}"
RUNS_DIR=${1:-runs}
MODE=${2:-}
TRAIN_CMD=${TRAIN_CMD:-python train.py}
resume=("resume=auto")  # continues RUNS_DIR/flow_gpu from its newest checkpoint, or starts it
if [ "$MODE" = "--quick" ]; then
  # shellcheck disable=SC2086
  $TRAIN_CMD experiment=flow_gpu trainer=smoke data.device=cpu data.batch_size=2 data.kitti_batch_size=1 threads=1 \
    runs_dir="$RUNS_DIR" "${resume[@]}"
else
  python -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 'gpu_train_flow.sh: torch ' + torch.__version__ + ' sees no CUDA device (a CPU-only torch build or no GPU); use --quick on a CPU')"
  # shellcheck disable=SC2086
  timeout -s TERM -k 60 "${TIME_LIMIT:-540}" $TRAIN_CMD experiment=flow_gpu trainer=gpu runs_dir="$RUNS_DIR" \
    "${resume[@]}" || echo "training stopped (exit $?: 143 = TIME_LIMIT, last.ckpt written; run again to resume)"
fi
python -c "from safetensors import safe_open; m = safe_open('$RUNS_DIR/flow_gpu/weights.safetensors', 'pt').metadata(); print('exported', '$RUNS_DIR/flow_gpu/weights.safetensors', m)"
