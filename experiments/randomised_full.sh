#!/usr/bin/env bash
# "Does memory matter?" on the randomised recipe IN FULL (issue 39 study (a)): the memory-less DeepestLSTMTinyPilotNet
# (single frames) against our memory network RecurrentTinyPilotNet (frames t-9, t-5, t), at least five training seeds
# each, with the data and the training recipe that made the shipped `*_dr` checkpoints (brains/weights/README.md, "The
# randomised recipe"), not shortened: 64 collection episodes (24 spline circuits, 8 of them pinned to no line and no
# walls, 8 twisty circuits; each both ways); tiny 16 epochs over every sample, patience 8; the memory network 12
# epochs, patience 8; one thread each. On the 2-core development machine collection takes about 30 minutes, a tiny
# seed 10-11 minutes and a memory seed 22 with a core to itself (three times that at nice 19 beside other work).
#   bash experiments/randomised_full.sh STUDY_DIR      # data once, then every seed (a rerun keeps finished seeds and
#                                                       # resumes an interrupted one from its last.ckpt)
#   SEEDS=0-9 WORKERS=2 bash experiments/randomised_full.sh STUDY_DIR   # the study's design: ten of each, two at a time
set -euo pipefail
STUDY=${1:?usage: randomised_full.sh STUDY_DIR}
DB=${DRIVEBENCH:-drivebench}
SEEDS=${SEEDS:-0-4}
WORKERS=${WORKERS:-1}
mkdir -p "$STUDY" && cd "$STUDY"
COLLECT=(--brain expert --randomise --direction both --recovery-noise 1.0 --laps 1 --max-sim-seconds 250
         --size 100x50 --split none)
collect() {  # collect NAME CIRCUITS [extra options]: once; a finished collection is kept
  local name=$1 circuits=$2
  shift 2
  [ -f "data/$name/manifest.json" ] || $DB dataset collect "${COLLECT[@]}" --circuits "$circuits" -o "data/$name" "$@"
}
collect dr_201 random:201,random:202,random:203,random:204,random:205,random:206,random:207,random:208
collect dr_209 random:209,random:210,random:211,random:212,random:213,random:214,random:215,random:216
collect dr_none random:217,random:218,random:219,random:220,random:221,random:222,random:223,random:224 \
    --variation line=none,walls=off
collect dr_306 twisty:306,twisty:331,twisty:305,twisty:336
collect dr_329 twisty:329,twisty:310,twisty:307,twisty:304
R="data/dr_201.recordings/*.mcap data/dr_209.recordings/*.mcap data/dr_none.recordings/*.mcap"
R="$R data/dr_306.recordings/*.mcap data/dr_329.recordings/*.mcap"
if [ ! -f data/dr_seq3/manifest.json ]; then
  # shellcheck disable=SC2086  # R holds globs
  $DB dataset build $R -o data/dr_single --size 100x50 --split episode:0.15 --label-brain expert
  # shellcheck disable=SC2086
  $DB dataset build $R -o data/dr_seq3 --size 100x50 --offsets=-9,-5,0 --split episode:0.15 --label-brain expert
fi
$DB train --model deepest_lstm_tiny_pilotnet --data data/dr_single --any-crop --epochs 16 --patience 8 --threads 1 \
    --seeds "$SEEDS" --workers "$WORKERS" -o runs/tiny_dr
$DB train --model recurrent_tiny_pilotnet --data data/dr_seq3 --epochs 12 --patience 8 --threads 1 \
    --seeds "$SEEDS" --workers "$WORKERS" -o runs/rtiny_dr
