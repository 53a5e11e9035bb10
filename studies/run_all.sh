#!/usr/bin/env bash
# The accuracy studies that run in minutes, in one go: the depth network's scale consistency on KITTI 06 and where
# KITTI 06's error comes from (scale vs direction). The longer ones (studies/flow_vs_classical.py,
# studies/scale_study.py, studies/kitti_flow_quality.py) run one by one as docs/ describes; speed: benchmarks/run_all.sh.
# Each study's JSON goes to OUT/NAME.json (stderr to OUT/NAME.err); the KITTI runs need ../shared/data.
#
#   studies/run_all.sh [OUT]        # default OUT: runs/studies
set -uo pipefail
cd "$(dirname "$0")/.."
OUT="${1:-runs/studies}"
KITTI=../shared/data/kitti_odom
mkdir -p "$OUT"
run() {  # run NAME COMMAND...
    local name="$1"
    shift
    echo "== $name (load $(cut -d' ' -f1 /proc/loadavg))"
    "$@" >"$OUT/$name.json" 2>"$OUT/$name.err"
    echo "rc=$?"
}
run depth_scale python studies/depth_scale_consistency.py
if python infer.py data=kitti_odom data.root="$KITTI" seq=06 out_dir="$OUT/kitti06" progress=false >"$OUT/kitti06.log" 2>&1
then
    run error_decomposition python studies/error_decomposition.py --gt "$KITTI/poses/06.txt" --pred "$OUT/kitti06/06.txt"
    run gt_constant_rate python studies/gt_constant_rate.py --gt "$KITTI/poses/06.txt" --run "$OUT/kitti06"
else
    echo "infer.py on KITTI 06 failed: see $OUT/kitti06.log" >&2
fi
