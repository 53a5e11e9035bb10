#!/usr/bin/env bash
# The training campaign: the long recipes of scripts/campaign.queue run one after another in the background, with
# one thread, each resumed from its newest checkpoint (train.py resume=auto), into a runs folder outside the work
# tree that outlives a session (docs/training.md#the-training-campaign).
#
#   scripts/campaign.sh start     # start or resume the queue in the background (returns at once); run it first
#   scripts/campaign.sh status    # per run: step of total, steps per hour, ETA, last loss; the queue's state
#   scripts/campaign.sh stop      # SIGTERM: the run in progress saves last.ckpt for its step and the queue ends
#   scripts/campaign.sh snapshot  # copy the resumable state into campaign/ (committed: a new machine resumes from it)
#   scripts/campaign.sh run       # the queue in the foreground (what start runs)
#
# The queue runs the code of the commit checked out when it starts (HEAD, exported to RUNS/code/SHA), so editing
# the work tree while it trains changes nothing under it; commit, then stop and start it to move it to new code.
# Run it with the project's Python (an activated venv, or PYTHON=/path/to/venv/bin/python).
# Environment: DFVO_RUNS_DIR (the runs folder, default ~/dfvo-runs), DFVO_KITTI_RAW_ROOT (default
# ../shared/data/kitti_raw beside the repository), CAMPAIGN_QUEUE (default scripts/campaign.queue),
# CAMPAIGN_THREADS (torch threads, default 1), PYTHON (default python), CAMPAIGN_CODE (run this folder's code
# instead of HEAD's export: tests), CAMPAIGN_SNAPSHOT (the committed state's folder, default campaign/: tests).
# Files: RUNS/campaign.log (every run's log lines, appended), RUNS/campaign.pid (the queue while it runs),
# RUNS/code/SHA (the code the queue runs),
# RUNS/NAME/ (each run: checkpoints/last.ckpt, weights.safetensors, finished.json when done; continue_from.safetensors
# when it was restored from committed weights alone).
set -uo pipefail
REPO="$(cd "$(dirname "$0")/.." && pwd)"
RUNS="${DFVO_RUNS_DIR:-$HOME/dfvo-runs}"
QUEUE="${CAMPAIGN_QUEUE:-$REPO/scripts/campaign.queue}"
THREADS="${CAMPAIGN_THREADS:-1}"
PYTHON="${PYTHON:-python}"
LOG="$RUNS/campaign.log"
PIDFILE="$RUNS/campaign.pid"
STOPFILE="$RUNS/campaign.stop"
SNAPSHOT="${CAMPAIGN_SNAPSHOT:-$REPO/campaign}"
CODE_ROOT="$RUNS/code"
CONTINUE_NAME="continue_from.safetensors"  # RUNS/NAME/: committed weights a run continues from (restore)
export DFVO_KITTI_RAW_ROOT="${DFVO_KITTI_RAW_ROOT:-$REPO/../shared/data/kitti_raw}"

say() { echo "[$(date '+%Y-%m-%d %H:%M:%S')] campaign: $*" | tee -a "$LOG"; }

queue_entries() {  # NAME<TAB>OVERRIDES per line, comments and blank lines dropped
  [ -f "$QUEUE" ] || { echo "campaign: no queue file $QUEUE (one run a line: NAME OVERRIDES...)" >&2; exit 2; }
  sed -e 's/#.*//' -e 's/[[:space:]]*$//' "$QUEUE" | awk 'NF { name = $1; $1 = ""; sub(/^ /, ""); print name "\t" $0 }'
}

running_pid() {
  [ -f "$PIDFILE" ] || return 1
  local pid; pid="$(cat "$PIDFILE")"
  kill -0 "$pid" 2>/dev/null && { echo "$pid"; return 0; }
  return 1
}

restore() {  # a run with no checkpoint here, whose state was committed in campaign/NAME/, continues from it
  local name="$1" dir="$RUNS/$1"
  if [ ! -f "$dir/finished.json" ] && [ ! -f "$dir/checkpoints/last.ckpt" ] && [ -f "$SNAPSHOT/$name/finished.json" ] \
      && [ -f "$SNAPSHOT/$name/weights.safetensors" ]; then  # a finished run: its network, for the runs after it
    # finished.json last, each copy whole before its rename: an interrupted restore leaves the run unfinished
    if mkdir -p "$dir" && cp "$SNAPSHOT/$name/weights.safetensors" "$dir/weights.safetensors.tmp" \
        && mv "$dir/weights.safetensors.tmp" "$dir/weights.safetensors" \
        && cp "$SNAPSHOT/$name/finished.json" "$dir/finished.json.tmp" && mv "$dir/finished.json.tmp" "$dir/finished.json"
    then
      say "$name: restored the committed finished run ($SNAPSHOT/$name/: weights.safetensors, finished.json)"
    else
      say "$name: could not restore the committed finished run from $SNAPSHOT/$name/"
    fi
  fi
  if [ ! -f "$dir/checkpoints/last.ckpt" ] && [ ! -f "$dir/finished.json" ] && [ -f "$SNAPSHOT/$name/last.ckpt" ]; then
    mkdir -p "$dir/checkpoints"
    cp "$SNAPSHOT/$name/last.ckpt" "$dir/checkpoints/last.ckpt"
    say "$name: restored the committed state $SNAPSHOT/$name/last.ckpt"
  fi
  # an unfinished run committed as its weights alone (a depth run: last.ckpt is too large to commit) continues from
  # them (train.py continue_from=RUNS/NAME/continue_from.safetensors: the epochs to go, the same rate schedule)
  if [ ! -f "$dir/checkpoints/last.ckpt" ] && [ ! -f "$dir/finished.json" ] && [ ! -f "$dir/$CONTINUE_NAME" ] \
      && [ ! -f "$SNAPSHOT/$name/finished.json" ] && [ ! -f "$SNAPSHOT/$name/last.ckpt" ] \
      && [ -f "$SNAPSHOT/$name/weights.safetensors" ]; then
    if mkdir -p "$dir" && cp "$SNAPSHOT/$name/weights.safetensors" "$dir/$CONTINUE_NAME.tmp" \
        && mv "$dir/$CONTINUE_NAME.tmp" "$dir/$CONTINUE_NAME"; then
      say "$name: no checkpoint here: continues from the committed weights $SNAPSHOT/$name/weights.safetensors" \
          "(continue_from: the optimiser and the pose network anew)"
    else
      say "$name: could not copy the committed weights $SNAPSHOT/$name/weights.safetensors"
    fi
  fi
}

code_snapshot() {  # RUNS/code/SHA: the committed tree of HEAD (not the work tree's edits), exported once
  local sha; sha="$(git -C "$REPO" rev-parse --short=12 HEAD)" || return 1
  local dir="$CODE_ROOT/$sha"
  if [ ! -f "$dir/train.py" ]; then
    rm -rf "$dir.tmp" && mkdir -p "$dir.tmp" && git -C "$REPO" archive HEAD | tar -x -C "$dir.tmp" && mv "$dir.tmp" "$dir"
  fi
  touch "$dir"
  # keep the three newest exports (~35 MB each: the shipped weights are part of the tree)
  ls -1dt "$CODE_ROOT"/*/ 2>/dev/null | tail -n +4 | xargs -r rm -rf
  echo "$dir"
}

run_queue() {
  mkdir -p "$RUNS"
  echo $$ > "$PIDFILE"
  rm -f "$STOPFILE"
  trap 'touch "$STOPFILE"; [ -n "${child:-}" ] && kill -TERM "$child" 2>/dev/null' TERM INT
  local code; code="${CAMPAIGN_CODE:-$(code_snapshot)}" || { say "cannot export the code of HEAD from $REPO"; rm -f "$PIDFILE"; exit 1; }
  [ -n "$(git -C "$REPO" status --porcelain --untracked-files=no 2>/dev/null)" ] && \
    say "note: the work tree has uncommitted changes; the queue runs the committed code of HEAD"
  say "queue $QUEUE, runs in $RUNS, $THREADS thread(s), code $code"
  while IFS=$'\t' read -r name overrides; do
    [ -f "$STOPFILE" ] && break
    restore "$name"
    if [ -f "$RUNS/$name/finished.json" ]; then
      say "$name: finished ($(tr -d '\n ' < "$RUNS/$name/finished.json")); next"
      continue
    fi
    local continued=""
    [ -f "$RUNS/$name/$CONTINUE_NAME" ] && continued="continue_from=$RUNS/$name/$CONTINUE_NAME"
    say "$name: start or resume: train.py $overrides${continued:+ $continued}"
    # shellcheck disable=SC2086  # the overrides are words of the queue line
    (cd "$code" && OMP_NUM_THREADS="$THREADS" exec "$PYTHON" train.py $overrides $continued name="$name" runs_dir="$RUNS" \
      threads="$THREADS" resume=auto trainer.print_every_n_steps=25 trainer.enable_progress_bar=false) \
      < /dev/null >> "$LOG" 2>&1 &
    child=$!
    wait "$child"; rc=$?
    # a signal to this script interrupts wait: wait again for the run to save its checkpoint
    while kill -0 "$child" 2>/dev/null; do wait "$child"; rc=$?; done
    child=
    case $rc in
      0) say "$name: finished" ;;
      130|143) say "$name: stopped (exit $rc), last.ckpt written; the next start resumes it"; break ;;
      *) say "$name: failed (exit $rc; its log lines above); the queue stops here (the runs after it may need it)"
         break ;;
    esac
  done < <(queue_entries)
  say "queue ended"
  rm -f "$PIDFILE"
}

status() {
  if pid="$(running_pid)"; then echo "campaign: running (pid $pid), log $LOG"; else echo "campaign: not running"; fi
  while IFS=$'\t' read -r name _; do
    local dir="$RUNS/$name" state="waiting" line=""
    if [ -f "$dir/finished.json" ]; then state="finished $(tr -d '\n ' < "$dir/finished.json")"
    elif [ -f "$dir/checkpoints/last.ckpt" ]; then state="started (last.ckpt $(date -r "$dir/checkpoints/last.ckpt" '+%F %T'))"
    fi
    line="$(grep -h -E "\] - step [0-9]+/" "$dir"/hydra/*/train.log 2>/dev/null | tail -1 | sed 's/.*\] - //')"
    echo "  $name: $state${line:+ | $line}"
  done < <(queue_entries)
}

stop() {
  if pid="$(running_pid)"; then
    touch "$STOPFILE"
    kill -TERM "$pid"
    echo "campaign: SIGTERM sent to $pid; the run in progress finishes its step and saves last.ckpt"
    for _ in $(seq 1 120); do kill -0 "$pid" 2>/dev/null || { echo "campaign: stopped"; return 0; }; sleep 1; done
    echo "campaign: still saving after 120 s (pid $pid)"
  else
    echo "campaign: not running"
  fi
}

snapshot() {  # the resumable state of each unfinished run, when small (< 50 MB: flow runs), weights otherwise; a
  # finished run's weights and finished.json (a new machine skips it, and the runs after it find its network)
  while IFS=$'\t' read -r name _; do
    local dir="$RUNS/$name"
    if [ -f "$dir/finished.json" ]; then
      [ -f "$dir/weights.safetensors" ] || continue
      if ! cmp -s "$dir/weights.safetensors" "$SNAPSHOT/$name/weights.safetensors" \
          || ! cmp -s "$dir/finished.json" "$SNAPSHOT/$name/finished.json"; then
        mkdir -p "$SNAPSHOT/$name"
        rm -f "$SNAPSHOT/$name/last.ckpt"
        cp "$dir/weights.safetensors" "$dir/finished.json" "$SNAPSHOT/$name/"
        echo "campaign: $name: finished: weights.safetensors and finished.json -> $SNAPSHOT/$name/"
      fi
      continue
    fi
    [ -f "$dir/checkpoints/last.ckpt" ] || continue
    mkdir -p "$SNAPSHOT/$name"
    local size; size=$(stat -c %s "$dir/checkpoints/last.ckpt")
    if [ "$size" -lt 50000000 ]; then
      cp "$dir/checkpoints/last.ckpt" "$SNAPSHOT/$name/last.ckpt"
      echo "campaign: $name: last.ckpt ($((size / 1000000)) MB) -> $SNAPSHOT/$name/"
    else
      cp "$dir/weights.safetensors" "$SNAPSHOT/$name/weights.safetensors"
      echo "campaign: $name: weights.safetensors -> $SNAPSHOT/$name/ (last.ckpt is $((size / 1000000)) MB)"
    fi
  done < <(queue_entries)
}

case "${1:-status}" in
  start)
    if pid="$(running_pid)"; then echo "campaign: already running (pid $pid); log $LOG"; exit 0; fi
    # a Python without the project's packages would fail in the background after start returned: check it here
    if ! "$PYTHON" -c "import hydra, lightning, torch" 2>/dev/null; then
      echo "campaign: PYTHON=$PYTHON cannot import hydra, lightning and torch; activate the project's venv or set" \
           "PYTHON=/path/to/venv/bin/python" >&2
      exit 2
    fi
    mkdir -p "$RUNS"
    nohup "$0" run > /dev/null 2>&1 &
    sleep 5
    if ! pid="$(running_pid)"; then  # every run finished, or the first one failed at once
      echo "campaign: the queue ended at once; its last lines:" >&2
      tail -n 5 "$LOG" >&2
      if tail -n 5 "$LOG" | grep -q "failed"; then exit 1; fi
      exit 0
    fi
    echo "campaign: started (pid $pid); log $LOG; 'scripts/campaign.sh status'"
    ;;
  run) run_queue ;;
  status) status ;;
  stop) stop ;;
  snapshot) snapshot ;;
  *) echo "usage: scripts/campaign.sh start|status|stop|snapshot|run" >&2; exit 2 ;;
esac
