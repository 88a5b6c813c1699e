#!/usr/bin/env bash
# "Does memory matter?" on the randomised recipe (issue 28 study (a)): the memory-less DeepestLSTMTinyPilotNet against
# our memory network RecurrentTinyPilotNet, five training seeds each. The recipe is brains/weights/README.md's
# randomised one, shortened alike for both networks to fit 2 shared CPU cores: 40 of its 64 collection episodes
# (8 spline circuits, 8 spline circuits pinned to no line / no walls, 4 twisty circuits; each both ways), and at
# most 6 epochs of 2,000 weighted draws, patience 4, one thread.
#   bash experiments/randomised_study.sh STUDY_DIR   # data once, then every seed (a rerun keeps finished seeds)
set -euo pipefail
STUDY=${1:?usage: randomised_study.sh STUDY_DIR}
DB=${DRIVEBENCH:-drivebench}
mkdir -p "$STUDY" && cd "$STUDY"
COLLECT=(--brain expert --randomise --direction both --recovery-noise 1.0 --laps 1 --max-sim-seconds 250
         --size 100x50 --split none)
collect() {  # collect NAME CIRCUITS [extra options]: once; a finished collection is kept
  local name=$1 circuits=$2
  shift 2
  [ -f "data/$name/manifest.json" ] || $DB dataset collect "${COLLECT[@]}" --circuits "$circuits" -o "data/$name" "$@"
}
collect dr_201 random:201,random:202,random:203,random:204,random:205,random:206,random:207,random:208
collect dr_none random:217,random:218,random:219,random:220,random:221,random:222,random:223,random:224 \
    --variation line=none,walls=off
collect dr_306 twisty:306,twisty:331,twisty:305,twisty:336
R="data/dr_201.recordings/*.mcap data/dr_none.recordings/*.mcap data/dr_306.recordings/*.mcap"
if [ ! -f data/dr_seq3/manifest.json ]; then
  # shellcheck disable=SC2086  # R holds globs
  $DB dataset build $R -o data/dr_single --size 100x50 --split episode:0.15 --label-brain expert
  # shellcheck disable=SC2086
  $DB dataset build $R -o data/dr_seq3 --size 100x50 --offsets=-9,-5,0 --split episode:0.15 --label-brain expert
fi
SHORT=(--epochs 6 --patience 4 --max-samples-per-epoch 2000 --threads 1)
$DB train --model deepest_lstm_tiny_pilotnet --data data/dr_single --any-crop "${SHORT[@]}" --seeds 0-4 -o runs/tiny_dr
$DB train --model recurrent_tiny_pilotnet --data data/dr_seq3 "${SHORT[@]}" --seeds 0-4 -o runs/rtiny_dr
