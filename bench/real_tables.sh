#!/bin/bash
# The recorded-data experiments (docs/real_data.md, "Experiments"). ETH/UCY, leave one scene
# out (eth hotel univ zara1 zara2): CV, V-LSTM, V-LSTM + SC, V-LSTM + ours (regressed goals),
# M = 20 modes for every model; CITR: CV, + SC, ours. Every learned row gets EPOCHS epochs;
# its learning rate is chosen on validation (seed 0 at each rate of GRID, the rate with the
# lowest best-epoch val minSADE), then seeds 1 and 2 at that rate; each test split is scored
# once, after every choice (`eval`: the whole split and the interacting subset). One run at
# a time, --threads 1.
#
#   bench/real_tables.sh data  [DATA] [RUNS]  # epo generate: DATA/eth_ucy/<scene>, DATA/citr
#   bench/real_tables.sh train [DATA] [RUNS]  # every run; resumable (rerun after a stop)
#   bench/real_tables.sh eval  [DATA] [RUNS]  # test splits: RUNS/eth_ucy/<scene>/eval-test, RUNS/citr/eval-test
#   bench/real_tables.sh table [DATA] [RUNS]  # the tables, beside bench/real_published.csv
#   bench/real_tables.sh cost  [DATA] [RUNS]  # measured seconds per epoch of each model (eth)
#
# DATA defaults to data/real, RUNS to runs/real. Env: SETS ("eth_ucy citr"), SCENES ("eth hotel
# univ zara1 zara2"), MODELS (ETH/UCY "vlstm sc epo"; CITR always without vlstm), EPOCHS (8),
# GRID ("1e-4 5e-4 1e-3"), MODES (20; CITR_MODES 6, the CITR dataset's), RAW_ETH
# (../shared/realdata/eth_ucy), RAW_CITR (../shared/realdata/citr), WORKERS (generation, 2),
# BATCHES (cost: 30 steps per model), EPO (the epo command; default the repository's
# .venv/bin/epo). Runs are RUNS/<set>[/<scene>]/{model}-lr{LR}-s{SEED}: a finished one (EPOCHS
# rows in metrics.csv) is skipped, an unfinished one resumes from its checkpoint; a dataset
# whose manifest is complete is not generated again. Two drivers may share RUNS when their
# SCENES / SETS / MODELS are disjoint (e.g. SCENES="eth hotel" on one core, the rest on the
# other).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
CMD=${1:?usage: bench/real_tables.sh data|train|eval|table|cost [DATA] [RUNS]}
DATA=${2:-data/real}; RUNS=${3:-runs/real}
E=${EPOCHS:-8}; GRID=${GRID:-"1e-4 5e-4 1e-3"}
SETS=${SETS:-"eth_ucy citr"}; SCENES=${SCENES:-"eth hotel univ zara1 zara2"}
EPO=${EPO:-$ROOT/.venv/bin/epo}; PY=$(dirname "$EPO")/python
die() { echo "error: $*" >&2; exit 2; }
log() { mkdir -p "$RUNS"; echo "$(date -u +%H:%M:%S) $*" | tee -a "$RUNS/queue.log"; }
finished() { [ -f "$1/metrics.csv" ] && awk -F, -v e="$E" 'NR>1 && $1==e {f=1} END {exit !f}' "$1/metrics.csv"; }
complete() { [ -f "$1/manifest.json" ] && "$PY" -c 'import json, sys; sys.exit(0 if json.load(open(sys.argv[1]))["complete"] else 1)' "$1/manifest.json"; }
for s in $SETS; do case $s in eth_ucy|citr) ;; *) die "SETS: expected eth_ucy and/or citr, got '$s'" ;; esac; done
for s in $SCENES; do case $s in eth|hotel|univ|zara1|zara2) ;; *) die "SCENES: expected some of eth hotel univ zara1 zara2, got '$s'" ;; esac; done
# the datasets (and runs folders) of SETS and SCENES: eth_ucy/eth ... citr
targets() {
  for s in $SETS; do
    if [ "$s" = citr ]; then echo citr; else for sc in $SCENES; do echo "eth_ucy/$sc"; done; fi
  done
}
train() {  # name model seed lr [extra args]   (D, R: the dataset and its runs folder)
  local name=$1 out=$R/$1 model=$2 seed=$3 lr=$4; shift 4
  finished "$out" && return 0
  log "start $R/$name"
  local rc=0
  "$EPO" train --no-progress --model "$model" --set backbone=vlstm "$@" --data "$D" --out "$out" \
    --seed "$seed" --epochs "$E" --lr "$lr" --batch-size 32 --threads 1 > "$out.log" 2>&1 || rc=$?
  log "end $R/$name rc=$rc"
}
choose() {  # group -> the rate with the lowest best-epoch val minSADE among its seed-0 runs
  flock "$R/chosen.lock" "$PY" "$ROOT/bench/choose_lr.py" "$R" "$1" "$E"  # two drivers may share RUNS
}
group() {  # model modes grid...   (extra train args in EXTRA)
  local model=$1 modes=$2; shift 2
  for lr in "$@"; do train "$model-lr$lr-s0" "$model" 0 "$lr" --modes "$modes" ${EXTRA:-}; done
  local lr; lr=$(choose "$model")
  for s in 1 2; do train "$model-lr$lr-s$s" "$model" "$s" "$lr" --modes "$modes" ${EXTRA:-}; done
}
has() { case " ${MODELS:-vlstm sc epo} " in *" $1 "*) return 0;; esac; return 1; }
case $CMD in
data)
  for t in $(targets); do
    D=$DATA/$t
    if complete "$D"; then log "data: $D complete"; continue; fi
    log "data: $D"
    if [ "$t" = citr ]; then
      "$EPO" generate vci --raw "${RAW_CITR:-$ROOT/../shared/realdata/citr}" --out "$D" \
        --workers "${WORKERS:-2}" --no-progress
    else
      "$EPO" generate eth-ucy --raw "${RAW_ETH:-$ROOT/../shared/realdata/eth_ucy}" \
        --test-scene "${t#eth_ucy/}" --out "$D" --workers "${WORKERS:-2}" --no-progress
    fi
  done ;;
train)
  for t in $(targets); do
    D=$DATA/$t; R=$RUNS/$t
    complete "$D" || die "$D: no complete dataset; run 'bench/real_tables.sh data $DATA $RUNS' first"
    mkdir -p "$R"
    log "train: data $D"
    if [ "$t" = citr ]; then
      m=${CITR_MODES:-6}
      has sc && EXTRA="" group sc "$m" $GRID
      has epo && EXTRA="--set goal_decoder=regress" group epo "$m" $GRID
    else
      m=${MODES:-20}
      has vlstm && EXTRA="" group vlstm "$m" $GRID
      has sc && EXTRA="" group sc "$m" $GRID
      has epo && EXTRA="--set goal_decoder=regress" group epo "$m" $GRID
    fi
  done
  log "train: done" ;;
eval)
  for t in $(targets); do
    D=$DATA/$t; R=$RUNS/$t
    [ -f "$R/chosen.csv" ] || die "$R/chosen.csv: no such file (no learning rate chosen yet); run 'bench/real_tables.sh train $DATA $RUNS' first"
    runs=()
    while IFS=, read -r g lr _; do
      for s in 0 1 2; do finished "$R/$g-lr$lr-s$s" && runs+=("$R/$g-lr$lr-s$s"); done
    done < "$R/chosen.csv"
    printf '%s\n' "${runs[@]}" > "$R/eval-test.runs.txt"
    "$EPO" evaluate "${runs[@]}" --model cv --data "$D" --split test --subset interacting \
      --out "$R/eval-test" --threads 1
  done ;;
table)
  [ -d "$RUNS/eth_ucy" ] || [ -d "$RUNS/citr" ] || die "$RUNS: neither eth_ucy/ nor citr/ (nothing trained yet); run 'bench/real_tables.sh train $DATA $RUNS' first"
  "$PY" "$ROOT/bench/real_tables.py" table "$RUNS" "$ROOT/bench/real_published.csv" ;;
cost)
  D=$DATA/eth_ucy/eth
  complete "$D" || die "$D: no complete dataset; run 'SETS=eth_ucy SCENES=eth bench/real_tables.sh data $DATA $RUNS' first"
  "$PY" "$ROOT/bench/real_tables.py" cost "$D" "${BATCHES:-30}" "${MODELS:-vlstm sc epo}" ;;
*) echo "error: expected data, train, eval, table or cost, got '$CMD'" >&2; exit 2 ;;
esac
