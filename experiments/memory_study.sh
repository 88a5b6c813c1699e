#!/usr/bin/env bash
# "Does memory matter?" with the paper's recipe in full (issue 39 study (b)): DeepestLSTMTinyPilotNet against memDCCP,
# ten training seeds each, the data and the training recipe that made the shipped checkpoints (brains/weights/README.md),
# not shortened: tiny 40 epochs over every sample with patience 8; memDCCP 15 epochs of 3,000 draws, patience 5; one
# thread each. On the 2-core development machine a tiny seed takes minutes and a memDCCP seed about 25-40 min.
#   bash experiments/memory_study.sh STUDY_DIR      # data once, then every seed (a rerun keeps finished seeds and
#                                                    # resumes an interrupted one from its last.ckpt)
set -euo pipefail
STUDY=${1:?usage: memory_study.sh STUDY_DIR}
DB=${DRIVEBENCH:-drivebench}
mkdir -p "$STUDY" && cd "$STUDY"
CIRCUITS=many_curves,nurburgring,monaco,extended_simple
if [ ! -f data/tiny/manifest.json ]; then
  $DB dataset collect --circuits $CIRCUITS --laps 1 --max-sim-seconds 400 -o data/paper_clean --size 100x50 \
      --split circuit:monaco
  $DB dataset collect --circuits $CIRCUITS --laps 1 --max-sim-seconds 400 --recovery-noise 1.0 -o data/paper_noisy \
      --split none
  R="data/paper_clean.recordings/*.mcap data/paper_noisy.recordings/*.mcap"
  # shellcheck disable=SC2086  # R holds globs
  $DB dataset build $R -o data/seq3 --size 100x50 --crop 0.5:1 --offsets=-9,-5,0 --split circuit:monaco \
      --label-brain explicit
  # shellcheck disable=SC2086
  $DB dataset build $R -o data/tiny --size 100x50 --crop 0.5:1 --split circuit:monaco --label-brain explicit
fi
SEEDS=${SEEDS:-0-9}
$DB train --model deepest_lstm_tiny_pilotnet --data data/tiny --epochs 40 --patience 8 --threads 1 --seeds "$SEEDS" \
    -o runs/tiny
$DB train --model memdccp --data data/seq3 --epochs 15 --patience 5 --max-samples-per-epoch 3000 --threads 1 \
    --seeds "$SEEDS" -o runs/memdccp
