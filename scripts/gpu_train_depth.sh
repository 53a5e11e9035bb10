#!/usr/bin/env bash
# Depth network of issue 18 on one GPU in <= 10 minutes (one H200): stereo + temporal self-supervision on KITTI raw
# mixed with the synthetic worlds of every scenario (drive, city, straight, highway; speeds 0.3-3 m/frame; KITTI camera
# height and intrinsics), with the supervised log-depth L1 on the synthetic samples (model.w_depth_supervised), then
# the scale benchmark of the result on KITTI 06 and on the held-out synthetic worlds.
#
#   DFVO_KITTI_RAW_ROOT=../shared/data/kitti_raw scripts/gpu_train_depth.sh            # the GPU recipe
#   TINY=1 DFVO_KITTI_RAW_ROOT=../shared/data/kitti_raw scripts/gpu_train_depth.sh     # CPU plumbing check (minutes)
#
# Settings (environment): RUNS_DIR (runs), NAME (depth_gpu), STEPS (training steps), BATCH, HEIGHT, WIDTH, WORKERS,
# SEEDS (synthetic worlds 0..SEEDS-1, seed s gets scenario s % 4), FRAMES (frames per world), W_SUP (supervised weight),
# TIME_LIMIT (seconds, 570), INIT (initial weights; empty: random init), KITTI_ODOM (KITTI odometry root for the
# benchmark; empty: skip it), EVAL (1: run the benchmark), TRAIN_CMD (the training command, default "python train.py").
# The CPU recipe of the 2026-12-01 candidates (not shipped) and their numbers are in dfvo/checkpoints/README.md.
set -euo pipefail
cd "$(dirname "$0")/.."

: "${DFVO_KITTI_RAW_ROOT:?set DFVO_KITTI_RAW_ROOT to the KITTI raw root (the folder holding 2011_09_26/...)}"
TINY=${TINY:-0}
RUNS_DIR=${RUNS_DIR:-runs}
NAME=${NAME:-depth_gpu}
TRAIN_CMD=${TRAIN_CMD:-python train.py}
INIT=${INIT-dfvo/checkpoints/depth.safetensors}
KITTI_ODOM=${KITTI_ODOM-../shared/data/kitti_odom}
W_SUP=${W_SUP:-0.1}
EVAL=${EVAL:-1}
if [ "$TINY" = 1 ]; then
  # a few steps on the CPU at a tiny size: checks data, loss, checkpoint and export, not the result
  STEPS=${STEPS:-2}; BATCH=${BATCH:-2}; HEIGHT=${HEIGHT:-64}; WIDTH=${WIDTH:-192}; WORKERS=${WORKERS:-0}
  SEEDS=${SEEDS:-4}; FRAMES=${FRAMES:-5}; TRAINER="trainer=default trainer.accelerator=cpu"; VAL_FRAMES=3
  THREADS=${THREADS:-1}; EVAL_ARGS="--num-frames 4 --worlds-per-scenario 1"
else
  # 320x96 as the shipped network (inference runs at the trained size; 640x192 costs 4x at inference as well)
  # the synthetic worlds are rendered by the CPU loader workers (~4 views per sample): the loader, not the GPU,
  # sets the pace; TIME_LIMIT stops a slower machine in time (SIGTERM: last.ckpt and the weights of the last
  # finished step are written, exit 143; running the script again continues it: resume=auto)
  STEPS=${STEPS:-1500}; BATCH=${BATCH:-16}; HEIGHT=${HEIGHT:-96}; WIDTH=${WIDTH:-320}; WORKERS=${WORKERS:-14}
  SEEDS=${SEEDS:-48}; FRAMES=${FRAMES:-24}; TRAINER="trainer=gpu"; VAL_FRAMES=12
  THREADS=${THREADS:-0}; EVAL_ARGS=""
fi
seeds=$(seq -s, 0 $((SEEDS - 1)))
init_arg=()
[ -n "$INIT" ] && init_arg=("model.init_from=$INIT")

start=$(date +%s)
# shellcheck disable=SC2086
timeout -k 20 "${TIME_LIMIT:-570}" $TRAIN_CMD model=depth_stereo data=kitti_raw_synthetic data.root="$DFVO_KITTI_RAW_ROOT" \
  data.height="$HEIGHT" data.width="$WIDTH" "data.seeds=[$seeds]" 'data.scenario=[drive,city,straight,highway]' \
  'data.speed=[0.3,3.0]' data.num_frames="$FRAMES" data.val_num_frames="$VAL_FRAMES" data.batch_size="$BATCH" \
  data.num_workers="$WORKERS" model.augment.gray_prob=0.2 model.w_depth_supervised="$W_SUP" "${init_arg[@]}" \
  $TRAINER trainer.max_steps="$STEPS" trainer.max_epochs=-1 trainer.enable_progress_bar=false \
  threads="$THREADS" runs_dir="$RUNS_DIR" name="$NAME" resume=auto \
  || echo "training stopped (exit $?: 143 = TIME_LIMIT, last.ckpt written; else an error)"
echo "training wall time: $(( $(date +%s) - start )) s"

weights="$RUNS_DIR/$NAME/weights.safetensors"
[ "$EVAL" = 1 ] || exit 0
# shellcheck disable=SC2086
python studies/depth_scale_consistency.py --depth "$weights" --synthetic all $EVAL_ARGS \
  > "$RUNS_DIR/$NAME/scale_synthetic.json"
if [ -n "$KITTI_ODOM" ] && [ -d "$KITTI_ODOM/sequences/06" ]; then
  python studies/depth_scale_consistency.py --depth "$weights" --root "$KITTI_ODOM" \
    > "$RUNS_DIR/$NAME/scale_kitti06.json"
fi
echo "weights: $weights; scale benchmark: $RUNS_DIR/$NAME/scale_*.json"
