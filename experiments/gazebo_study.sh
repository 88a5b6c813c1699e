#!/usr/bin/env bash
# The sim-to-sim experiment (issue 30), networks trained in the gazebo look (textured asphalt and grass, shading, the
# sun's shadows, a cloudy sky: docs/look.md), each recipe shortened exactly as its flat-look study was:
# - paper: the paper's recipe re-collected in the gazebo look (experiments/memory_study.sh's circuits, laps, recovery
#   bursts, labels and crop); five seeds of DeepestLSTMTinyPilotNet (tiny_gz), three of memDCCP (memdccp_gz);
# - randomised: experiments/randomised_study.sh's recipe with the look drawn per episode too (--looks flat,gazebo);
#   five seeds of DeepestLSTMTinyPilotNet (tiny_dr_looks).
# Training: at most 6 epochs of 2,000 weighted draws, patience 4, one thread, as brains/weights/study/*.
#   bash experiments/gazebo_study.sh STUDY_DIR [paper|randomised|all]   # data once; a rerun keeps finished seeds
set -euo pipefail
STUDY=${1:?usage: gazebo_study.sh STUDY_DIR [paper|randomised|all]}
WHAT=${2:-all}
DB=${DRIVEBENCH:-drivebench}
WORKERS=${WORKERS:-1}
mkdir -p "$STUDY" && cd "$STUDY"
SHORT=(--epochs 6 --patience 4 --max-samples-per-epoch 2000 --threads 1 --workers "$WORKERS")

paper() {
  local circuits=many_curves,nurburgring,monaco,extended_simple gazebo=(--renderer gl --variation look=gazebo)
  if [ ! -f data/tiny/manifest.json ]; then
    $DB dataset collect --circuits $circuits --laps 1 --max-sim-seconds 400 "${gazebo[@]}" -o data/paper_clean \
        --size 100x50 --split circuit:monaco
    $DB dataset collect --circuits $circuits --laps 1 --max-sim-seconds 400 "${gazebo[@]}" --recovery-noise 1.0 \
        -o data/paper_noisy --split none
    local r="data/paper_clean.recordings/*.mcap data/paper_noisy.recordings/*.mcap"
    # shellcheck disable=SC2086  # r holds globs
    $DB dataset build $r -o data/seq3 --size 100x50 --crop 0.5:1 --offsets=-9,-5,0 --split circuit:monaco \
        --label-brain explicit
    # shellcheck disable=SC2086
    $DB dataset build $r -o data/tiny --size 100x50 --crop 0.5:1 --split circuit:monaco --label-brain explicit
  fi
  $DB train --model deepest_lstm_tiny_pilotnet --data data/tiny "${SHORT[@]}" --seeds 0-4 -o runs/tiny_gz
  $DB train --model memdccp --data data/seq3 "${SHORT[@]}" --seeds 0-2 -o runs/memdccp_gz
}

randomised() {
  local collect=(--brain expert --randomise --looks flat,gazebo --renderer gl --direction both --recovery-noise 1.0
                 --laps 1 --max-sim-seconds 250 --size 100x50 --split none)
  local name circuits
  for name in dr_201 dr_none dr_306; do
    case $name in
      dr_201) circuits=random:201,random:202,random:203,random:204,random:205,random:206,random:207,random:208 ;;
      dr_none) circuits=random:217,random:218,random:219,random:220,random:221,random:222,random:223,random:224 ;;
      dr_306) circuits=twisty:306,twisty:331,twisty:305,twisty:336 ;;
    esac
    local pin=()
    [ "$name" = dr_none ] && pin=(--variation line=none,walls=off)
    [ -f "data/$name/manifest.json" ] || $DB dataset collect "${collect[@]}" --circuits "$circuits" -o "data/$name" \
        "${pin[@]}"
  done
  if [ ! -f data/dr_single/manifest.json ]; then
    # shellcheck disable=SC2086  # globs
    $DB dataset build data/dr_201.recordings/*.mcap data/dr_none.recordings/*.mcap data/dr_306.recordings/*.mcap \
        -o data/dr_single --size 100x50 --split episode:0.15 --label-brain expert
  fi
  $DB train --model deepest_lstm_tiny_pilotnet --data data/dr_single --any-crop "${SHORT[@]}" --seeds 0-4 \
      -o runs/tiny_dr_looks
}

case $WHAT in
  paper) paper ;;
  randomised) randomised ;;
  all) paper; randomised ;;
  *) echo "gazebo_study.sh: unknown part '$WHAT' (paper, randomised or all)" >&2; exit 2 ;;
esac
