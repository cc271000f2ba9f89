#!/bin/bash
# Paper Tab. 2 on an exiD-layout dataset (docs/exid.md, "The experiment"): every learned row
# gets EPOCHS epochs; its learning rate is chosen on the validation split (seed 0 at each rate
# of GRID, the rate with the lowest best-epoch val minSADE), then seeds 1 and 2 at that rate;
# the test split is scored once, after every choice (`eval`). One run at a time, --threads 1.
#
#   bench/exid_tab2.sh train [DATA] [RUNS]   # all runs; resumable (rerun after a stop)
#   bench/exid_tab2.sh eval  [DATA] [RUNS]   # test split of the chosen runs + CV: RUNS/eval-test
#   bench/exid_tab2.sh table [DATA] [RUNS]   # RUNS/eval-test as markdown beside the paper's
#
# DATA defaults to data/exid (made by `epo generate exid`), RUNS to runs/exid-tab2.
# Env: BACKBONES ("vlstm vibes hivt"), MODELS ("vlstm sc epo tgl"; TGL on V-LSTM only, as in
# the paper), EPOCHS (8), GRID ("2e-4 5e-4 1e-3"; TGL "5e-4 1e-3": its epoch costs 5x ours),
# ONLY (eval: a regex on the group names of RUNS/chosen.csv, e.g. '^tgl-'), EPO (the epo
# command; default the repository's .venv/bin/epo).
# Runs are named {model}-{backbone}-lr{LR}-s{SEED}: a finished one (EPOCHS rows in
# metrics.csv) is skipped, an unfinished one resumes from its checkpoint. Two drivers may
# share RUNS when their MODELS / BACKBONES are disjoint (e.g. TGL on one core, the rest on
# the other: MODELS=tgl ... & MODELS="vlstm sc epo" ...).
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
CMD=${1:?usage: bench/exid_tab2.sh train|eval|table [DATA] [RUNS]}
D=${2:-data/exid}; R=${3:-runs/exid-tab2}
E=${EPOCHS:-8}; GRID=${GRID:-"2e-4 5e-4 1e-3"}
EPO=${EPO:-$ROOT/.venv/bin/epo}; PY=$(dirname "$EPO")/python
die() { echo "error: $*" >&2; exit 2; }
log() { echo "$(date -u +%H:%M:%S) $*" | tee -a "$R/queue.log"; }
finished() { [ -f "$1/metrics.csv" ] && awk -F, -v e="$E" 'NR>1 && $1==e {f=1} END {exit !f}' "$1/metrics.csv"; }
train() {  # name model backbone seed lr [extra args]
  local name=$1 out=$R/$1 model=$2 bb=$3 seed=$4 lr=$5; shift 5
  finished "$out" && return 0
  log "start $name"
  local rc=0
  "$EPO" train --no-progress --model "$model" --set backbone="$bb" "$@" --data "$D" --out "$out" \
    --seed "$seed" --epochs "$E" --lr "$lr" --batch-size 32 --threads 1 > "$out.log" 2>&1 || rc=$?
  log "end $name rc=$rc"
}
choose() {  # group -> the rate with the lowest best-epoch val minSADE among its seed-0 runs
  flock "$R/chosen.lock" "$PY" "$ROOT/bench/choose_lr.py" "$R" "$1" "$E"  # two drivers may share RUNS
}
group() {  # model backbone grid... (extra train args in EXTRA)
  local model=$1 bb=$2 g=$1-$2; shift 2
  for lr in "$@"; do train "$g-lr$lr-s0" "$model" "$bb" 0 "$lr" ${EXTRA:-}; done
  local lr; lr=$(choose "$g")
  for s in 1 2; do train "$g-lr$lr-s$s" "$model" "$bb" "$s" "$lr" ${EXTRA:-}; done
}
has() { case " ${MODELS:-vlstm sc epo tgl} " in *" $1 "*) return 0;; esac; return 1; }
case $CMD in
train)
  mkdir -p "$R"
  log "train: data $D"
  for bb in ${BACKBONES:-vlstm vibes hivt}; do
    has vlstm && EXTRA="" group vlstm "$bb" $GRID
    has sc && EXTRA="" group sc "$bb" $GRID
    has epo && EXTRA="--set goal_decoder=candidates" group epo "$bb" $GRID
    if has tgl && [ "$bb" = vlstm ]; then EXTRA="" group tgl vlstm 5e-4 1e-3; fi
  done
  log "train: done" ;;
eval)
  [ -f "$R/chosen.csv" ] || die "$R/chosen.csv: no such file (no learning rate chosen yet); run 'bench/exid_tab2.sh train $D $R' first"
  runs=()
  while IFS=, read -r g lr _; do
    [[ $g =~ ${ONLY:-.} ]] || continue
    for s in 0 1 2; do finished "$R/$g-lr$lr-s$s" && runs+=("$R/$g-lr$lr-s$s"); done
  done < "$R/chosen.csv"
  printf '%s\n' "${runs[@]}" > "$R/eval-test.runs.txt"
  "$EPO" evaluate "${runs[@]}" --model cv --data "$D" --split test --out "$R/eval-test" --threads 1 ;;
table)
  [ -f "$R/eval-test/results_runs.csv" ] || die "$R/eval-test/results_runs.csv: no such file (the test split is not scored yet); run 'bench/exid_tab2.sh eval $D $R' first"
  "$PY" "$ROOT/bench/exid_tab2_table.py" "$R/eval-test" "$R/chosen.csv" ;;
*) echo "error: expected train, eval or table, got '$CMD'" >&2; exit 2 ;;
esac
