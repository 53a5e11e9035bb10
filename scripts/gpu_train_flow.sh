#!/usr/bin/env bash
# Train the flow network on one H200-class GPU within 10 minutes: the synthetic driving worlds (all scenarios incl.
# highway, 0.3-3 m/frame, frame skips 1-3) rendered ON THE GPU (SyntheticWorld(device="cuda")), supervised, then
# mixed with self-supervised KITTI raw pairs; bf16 autocast, channels-last. Writes OUT/last.pt (resumable: run the
# same command again) and OUT/weights.safetensors (the inference export: infer.py flow.checkpoint=OUT/weights.safetensors),
# and the log OUT/train.log (one JSON line per log/eval; held-out AEPE per scenario).
#
#   scripts/gpu_train_flow.sh [OUT]            # the GPU recipe (NOT YET RUN on a GPU: none was at hand)
#   scripts/gpu_train_flow.sh [OUT] --quick    # tiny CPU run of the same plumbing (2 worlds of 6 frames, 3
#                                              # supervised + 2 mixed steps: 1.2 min on the 2-core dev machine)
#
# Time on the GPU: training stops at 9 minutes from the start of the Python process's clock (rendering, at most
# 2.5 min of it, included; the phases and learning-rate drops follow the clock when it ends before the steps), then
# saves; with interpreter start-up and the export check the whole script stays under 10 minutes.
# Needs a CUDA build of torch (the repository's pinned wheel is the CPU one): the full mode stops with one line when
# torch sees no CUDA device. The result is a candidate, not a shipped model: compare it with
#   python studies/flow_vs_classical.py --checkpoint OUT/weights.safetensors
# (docs/flow.md) before it replaces dfvo/checkpoints/flow.safetensors.
#
# Environment: KITTI_RAW (default /work/shared/data/kitti_raw/2011_09_26; unset or missing -> no self-supervised
# phase), INIT (weights to start from; default the shipped dfvo/checkpoints/flow.safetensors).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/flow_gpu}
MODE=${2:-}
KITTI_RAW=${KITTI_RAW:-/work/shared/data/kitti_raw/2011_09_26}
INIT=${INIT:-dfvo/checkpoints/flow.safetensors}
mkdir -p "$OUT"
MIX=(--mix-steps 5000 --kitti-raw "$KITTI_RAW")
[ -d "$KITTI_RAW" ] || MIX=(--mix-steps 0)
if [ "$MODE" = "--quick" ]; then
  python benchmarks/flow_training_run.py --out "$OUT" --cache "$OUT/cache" --init "$INIT" --device auto \
    --worlds 2 --frames 6 --batch 2 --kitti-batch 1 --sup-steps 3 "${MIX[@]/5000/2}" \
    --log-every 1 --save-every 2 --eval-every 1000 --threads 1 --max-minutes 15 2>&1 | tee -a "$OUT/train.log"
else
  python -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 'gpu_train_flow.sh: torch ' + torch.__version__ + ' sees no CUDA device (a CPU-only torch build or no GPU); use --quick on a CPU')"
  python benchmarks/flow_training_run.py --out "$OUT" --cache "$OUT/cache" --init "$INIT" \
    --device cuda --render-device cuda --amp bf16 --channels-last --threads 8 \
    --worlds 96 --frames 40 --render-minutes 2.5 --batch 64 --kitti-batch 16 \
    --sup-steps 20000 "${MIX[@]}" --lr 4e-4 --mix-lr 1e-4 \
    --max-minutes 9 --log-every 100 --save-every 500 --eval-every 2000 2>&1 | tee -a "$OUT/train.log"
fi
python -c "from safetensors import safe_open; m = safe_open('$OUT/weights.safetensors', 'pt').metadata(); print('exported', '$OUT/weights.safetensors', m)"
