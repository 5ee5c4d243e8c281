#!/usr/bin/env bash
# Write the tracks of the cases a refactoring must leave byte-identical, to compare two commits:
#
#   bash scripts/track_cases.sh OUT_DIR
#   (cd ../old-checkout && bash scripts/track_cases.sh /tmp/old) && diff -r /tmp/old OUT_DIR
#
# WILDTRACK exact and with the simulated detector (seeds 1-3), both matchers; MultiviewX's
# annotated boxes; the synthetic plaza; WILDTRACK with unsynchronised cameras. Needs ../shared.
set -euo pipefail
cd "$(dirname "$0")/.."
out=$1
mkdir -p "$out"
wildtrack=${CBLRS_WILDTRACK:-../shared/data/wildtrack}
multiviewx=${CBLRS_MULTIVIEWX:-../shared/data/multiviewx}
# The positional data set (the spelling before --dataset, still accepted) runs on old commits too.
track() { python -m cblrs.cli.main track "$@" --quiet > /dev/null; }
for matcher in fusion paper; do
    track "$wildtrack" --out "$out/wt-$matcher-exact.txt" --matcher "$matcher"
    for seed in 1 2 3; do
        track "$wildtrack" --out "$out/wt-$matcher-noisy$seed.txt" --matcher "$matcher" \
            --drop 0.2 --jitter 0.05 --seed "$seed"
    done
done
track "$multiviewx" --out "$out/mvx-exact.txt" 2> /dev/null
track synthetic:plaza --out "$out/plaza-noisy1.txt" --drop 0.2 --jitter 0.05 --seed 1
track "$wildtrack" --out "$out/wt-async.txt" --clock-offset-ms 80 --clock-jitter-ms 20 \
    --drop-messages 0.05 --clock-seed 1
(cd "$out" && md5sum ./*.txt)
