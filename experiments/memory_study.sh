#!/usr/bin/env bash
# "Does memory matter?" on the paper's own terms (issue 28 study (b)): DeepestLSTMTinyPilotNet against memDCCP,
# five training seeds each, the paper's data recipe (brains/weights/README.md), training shortened the same way for
# both networks to fit 2 CPU cores: at most 6 epochs of 2,000 weighted draws, patience 4, one thread.
#   bash experiments/memory_study.sh STUDY_DIR      # data once, then every seed (a rerun keeps finished seeds)
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
SHORT=(--epochs 6 --patience 4 --max-samples-per-epoch 2000 --threads 1)
$DB train --model deepest_lstm_tiny_pilotnet --data data/tiny "${SHORT[@]}" --seeds 0-4 -o runs/tiny
$DB train --model memdccp --data data/seq3 "${SHORT[@]}" --seeds 0-4 -o runs/memdccp
