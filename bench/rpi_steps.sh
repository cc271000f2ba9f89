#!/bin/bash
# The S-steps ablation of the paper (App. G.3, Fig. "Predictive performance of the initial (red)
# and optimized strategy (blue) as a function of the number of optimization steps on the RPI
# validation dataset"; docs/experiment_rpi.md, "Number of optimization steps"): for each S of
# STEPS and each seed of SEEDS, ours (V-LSTM + Ours) is trained with S LM steps in the game
# layer (`epo train --model epo --lm-steps S`); then every run's best.pt is scored on the
# validation split (`epo evaluate --split val`: minSADE of the optimized strategies and, as
# init_minSADE, of the learned initial strategies) and bench/rpi_steps_plot.py draws minSADE
# against S (red: initial, blue: optimized) into OUT/rpi_steps.png and OUT/rpi_steps.csv.
#
#   bench/rpi_steps.sh DATA OUT
#
# DATA: an RPI dataset (`epo generate rpi`). OUT: runs in OUT/runs/S{S}-s{SEED}, the evaluation
# in OUT/eval-val (results.md, results.csv, results_runs.csv), the figure and its CSV in OUT.
# Resumable: a stopped run continues from its checkpoint when the script is run again; a
# finished one (EPOCHS rows in metrics.csv) is skipped.
# Env: STEPS ("1 2 4 8"), SEEDS ("0 1 2"), EPOCHS (12), LR (5e-5, the paper's for ours),
# TRAIN_ARGS (more `epo train` options, e.g. "--set hist_width=32"), EPO (the epo command;
# default the repository's .venv/bin/epo).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
D=${1:?usage: bench/rpi_steps.sh DATA OUT}
O=${2:?usage: bench/rpi_steps.sh DATA OUT}
STEPS=${STEPS:-"1 2 4 8"}; SEEDS=${SEEDS:-"0 1 2"}; E=${EPOCHS:-12}; LR=${LR:-5e-5}
EPO=${EPO:-$ROOT/.venv/bin/epo}; PY=$(dirname "$EPO")/python
read -r -a EXTRA <<< "${TRAIN_ARGS:-}"
die() { echo "error: $*" >&2; exit 2; }
[ -f "$D/manifest.json" ] || die "DATA: $D is not a dataset folder (no manifest.json)"
[ -x "$EPO" ] || command -v "$EPO" > /dev/null || die "EPO: $EPO is not a command"
mkdir -p "$O/runs"
O=$(cd "$O" && pwd)  # absolute run paths in results_runs.csv
log() { echo "$(date -u +%H:%M:%S) $*" | tee -a "$O/queue.log"; }
finished() { [ -f "$1/metrics.csv" ] && awk -F, -v e="$E" 'NR>1 && $1==e {f=1} END {exit !f}' "$1/metrics.csv"; }
runs=()
for S in $STEPS; do
  for seed in $SEEDS; do
    out=$O/runs/S$S-s$seed
    runs+=("$out")
    finished "$out" && continue
    log "start S=$S seed=$seed"
    rc=0
    "$EPO" train --model epo --lm-steps "$S" --seed "$seed" --epochs "$E" --lr "$LR" \
      --batch-size 32 --threads 1 --no-progress --no-tensorboard "${EXTRA[@]}" \
      --data "$D" --out "$out" > "$out.log" 2>&1 || rc=$?
    log "end S=$S seed=$seed rc=$rc"
    [ "$rc" = 0 ] || die "training S=$S seed=$seed failed (rc $rc): see $out.log"
  done
done
"$EPO" evaluate "${runs[@]}" --data "$D" --split val --threads 1 --out "$O/eval-val"
"$PY" "$ROOT/bench/rpi_steps_plot.py" "$O/eval-val/results_runs.csv" --out "$O/rpi_steps.png"
