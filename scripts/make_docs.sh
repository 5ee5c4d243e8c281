#!/usr/bin/env bash
# Regenerate every table and figure under docs/ with the cblrs CLI (nothing is typed by hand).
#
#   scripts/make_docs.sh            # full runs (about 5-10 minutes on 2 cores)
#   QUICK=1 scripts/make_docs.sh    # fewer repeats and pixels, for a smoke test
#
# WILDTRACK is taken from $CBLRS_WILDTRACK or ../shared/data/wildtrack; without it the
# benchmarks use a built-in camera and the WILDTRACK parts are skipped.
set -euo pipefail
cd "$(dirname "$0")/.."

# One thread per library, so that numpy's BLAS does not fight the other jobs for the cores
# (the timings then compare the methods, not the thread scheduler).
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1

results=docs/results
figures=docs/figures
mkdir -p "$results" "$figures"

repeats=5
pixels=100000
if [[ "${QUICK:-0}" == "1" ]]; then
    repeats=2
    pixels=20000
fi

wildtrack="${CBLRS_WILDTRACK:-../shared/data/wildtrack}"
tracking="plaza,roundabout"
if [[ -d "$wildtrack/calibrations" ]]; then
    tracking="wildtrack,$tracking"
    scenes="wildtrack,plaza"
else
    scenes="plaza"
fi

echo "== benchmarks (lookup, render, claims, tracker, pipeline)" >&2
cblrs bench all --repeats "$repeats" --n "$pixels" --out "$results" --figures "$figures" --quiet \
    > /dev/null

echo "== experiment: targeting" >&2
cblrs experiment targeting --tracking "$tracking" --out "$results" --figures "$figures" \
    > /dev/null

echo "== experiment: resolution" >&2
cblrs experiment resolution --scenes "$scenes" --out "$results" --figures "$figures" > /dev/null

if [[ -d "$wildtrack/calibrations" ]]; then
    echo "== experiment: clicked calibration (N points per camera vs the lab calibration)" >&2
    cblrs experiment calibration --dataset "$wildtrack" --out "$results" --figures "$figures" \
        --quiet > /dev/null
fi

if [[ -d "$wildtrack/calibrations" ]]; then
    echo "== WILDTRACK tracking: both matchers, exact and simulated detectors" >&2
    scratch=$(mktemp -d)
    {
        echo "### WILDTRACK tracking (all 200 annotated frames, 7 cameras, annotated boxes as detections)"
        echo
        echo "Commands: \`cblrs track --dataset $wildtrack --out T.txt --matcher M [detector options]\` then"
        echo "\`cblrs eval --dataset $wildtrack T.txt --json\`."
        echo
        echo "| matcher | detector | HOTA | DetA | AssA | LocA | MOTA | IDF1 |"
        echo "|---|---|---|---|---|---|---|---|"
        for matcher in fusion paper; do
            for detector in "exact" "--drop 0.2 --jitter 0.05 --seed 1" \
                "--drop 0.2 --jitter 0.05 --seed 2" "--drop 0.2 --jitter 0.05 --seed 3"; do
                options=""
                [[ "$detector" != "exact" ]] && options="$detector"
                # shellcheck disable=SC2086
                cblrs track --dataset "$wildtrack" --out "$scratch/t.txt" --matcher "$matcher" $options \
                    --quiet > /dev/null
                cblrs eval --dataset "$wildtrack" "$scratch/t.txt" --json | python -c "
import json, sys
m = json.load(sys.stdin)
print('| $matcher | ${detector} | ' + ' | '.join(f'{m[k]:.2f}' for k in
      ('HOTA', 'DetA', 'AssA', 'LocA', 'MOTA', 'IDF1')) + ' |')"
            done
        done
        echo
        echo "Held-out check (frames tracked and scored separately):"
        echo
        echo "| matcher | frames | HOTA | DetA | AssA | LocA | MOTA | IDF1 |"
        echo "|---|---|---|---|---|---|---|---|"
        for frames in 0:495 500:995; do
            cblrs track --dataset "$wildtrack" --out "$scratch/t.txt" --frames "$frames" --quiet > /dev/null
            cblrs eval --dataset "$wildtrack" "$scratch/t.txt" --frames "$frames" --json | python -c "
import json, sys
m = json.load(sys.stdin)
print('| fusion | $frames | ' + ' | '.join(f'{m[k]:.2f}' for k in
      ('HOTA', 'DetA', 'AssA', 'LocA', 'MOTA', 'IDF1')) + ' |')"
        done
    } > "$results/wildtrack_tracking.md"
    rm -rf "$scratch"
fi

multiviewx="${CBLRS_MULTIVIEWX:-../shared/data/multiviewx}"
model="${CBLRS_DETECTOR_MODEL:-../shared/models/yolox_nano.onnx}"
if [[ -d "$multiviewx/Image_subsets" && -f "$model" ]]; then
    echo "== real frames: on-camera cost, tracking from images through the detector" >&2
    cblrs bench camera --dataset "$multiviewx" --model "$model" --repeats "$repeats" \
        --out "$results" --quiet > /dev/null
    cblrs bench detect --dataset "$multiviewx" --model "$model" --out "$results" --quiet \
        > /dev/null
    demo_real=$(mktemp -d)
    cblrs demo --dataset "$multiviewx" --detector onnx --model "$model" --out "$demo_real" \
        --quiet > /dev/null
    python - "$demo_real/multiviewx" "$figures" <<'PY'
import sys
from pathlib import Path

import cv2

demo, figures = Path(sys.argv[1]), Path(sys.argv[2])
for source, target, width in [
    ("overlay_Camera2.png", "demo_multiviewx_overlay_Camera2.jpg", 1100),
    ("trajectories.png", "demo_multiviewx_trajectories.png", 1400),
]:
    image = cv2.imread(str(demo / source), cv2.IMREAD_COLOR)
    scale = width / image.shape[1]
    if scale < 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    # A real photograph: JPEG keeps the repository small.
    options = [cv2.IMWRITE_JPEG_QUALITY, 85] if target.endswith(".jpg") else [
        cv2.IMWRITE_PNG_COMPRESSION, 9]
    cv2.imwrite(str(figures / target), image, options)
PY
    rm -rf "$demo_real"
fi

if [[ -d "$wildtrack/calibrations" ]]; then
    echo "== pseudo coordinates: tracking with a key, and recovering its transform (about 3 minutes)" >&2
    scratch=$(mktemp -d)
    cblrs pseudo keygen --out "$scratch/site.key" > /dev/null
    {
        echo "| matcher | detector | HOTA plain | HOTA pseudo | difference |"
        echo "|---|---|---|---|---|"
        for matcher in fusion paper; do
            for detector in "exact" "--drop 0.2 --jitter 0.05 --seed 1" \
                "--drop 0.2 --jitter 0.05 --seed 2" "--drop 0.2 --jitter 0.05 --seed 3"; do
                options=""
                [[ "$detector" != "exact" ]] && options="$detector"
                # shellcheck disable=SC2086
                cblrs track --dataset "$wildtrack" --out "$scratch/plain.txt" --matcher "$matcher" \
                    $options --quiet > /dev/null
                # shellcheck disable=SC2086
                cblrs track --dataset "$wildtrack" --out "$scratch/pseudo.txt" --matcher "$matcher" \
                    $options --key "$scratch/site.key" --quiet > /dev/null
                plain=$(cblrs eval --dataset "$wildtrack" "$scratch/plain.txt" --json)
                pseudo=$(cblrs eval --dataset "$wildtrack" "$scratch/pseudo.txt" \
                    --key "$scratch/site.key" --json)
                python -c "
import json, sys
plain, pseudo = json.loads(sys.argv[1])['HOTA'], json.loads(sys.argv[2])['HOTA']
print(f'| $matcher | ${detector} | {plain:.2f} | {pseudo:.2f} | {pseudo - plain:+.2f} |')" \
                    "$plain" "$pseudo"
            done
        done
    } > "$results/pseudo_tracking.md"
    rm -rf "$scratch"
    cblrs experiment pseudo --dataset "$wildtrack" --out "$results" --quiet > /dev/null
fi

if [[ -d "$wildtrack/calibrations" ]] && python -c "import norfair" 2> /dev/null; then
    echo "== cblrs track beside homography + norfair, whole process (about 2 minutes)" >&2
    cblrs bench track --dataset "$wildtrack" --repeats "$repeats" --out "$results" --quiet \
        > /dev/null
fi

echo "== experiment: counts (analytics on tracks vs on ground truth, about 1 minute)" >&2
count_scenes="plaza,roundabout,roundabout-traffic"
[[ -d "$wildtrack/calibrations" ]] && count_scenes="wildtrack,$count_scenes"
cblrs experiment counts --scenes "$count_scenes" --out "$results" --figures "$figures" --quiet \
    > /dev/null

echo "== experiment: identities and OD across the planes of a synthetic street (about 8 minutes)" >&2
planes_options=""
[[ "${QUICK:-0}" == "1" ]] && planes_options="--seeds 1 --people 16 --cars 4"
# shellcheck disable=SC2086
cblrs experiment planes $planes_options --out "$results" --quiet > /dev/null

if [[ -d "$wildtrack/calibrations" && "${QUICK:-0}" != "1" ]]; then
    echo "== experiment: identity where it is hard (issue 19's cases, about 15 minutes each)" >&2
    cblrs experiment tracking --out "$results" --quiet > /dev/null
    cblrs experiment tracking --without-rules --out "$results" --quiet > /dev/null
fi

echo "== bench: analytics (an hour of 200 tracks at 10 Hz)" >&2
analytics_hours=1
[[ "${QUICK:-0}" == "1" ]] && analytics_hours=0.1
cblrs bench analytics --hours "$analytics_hours" --out "$results" --quiet > /dev/null

echo "== dashboard: 200 live tracks at 10 Hz in headless Chromium; screenshots of the browser test" >&2
if command -v mosquitto > /dev/null && [[ -x /usr/bin/chromium ]]; then
    cblrs bench dashboard --out "$results" --quiet > /dev/null
    if [[ -d "$wildtrack/calibrations" ]]; then
        # The browser test's own screenshots: a real matcher, cameras and the viewer's page.
        CBLRS_SCREENSHOTS="$figures" python -m pytest -q -p no:cacheprovider \
            tests/dashboard/test_dashboard_browser.py > /dev/null
    fi
fi

echo "== MQTT runtime: throughput and latency through Mosquitto (about 10 minutes)" >&2
if command -v mosquitto > /dev/null; then
    mqtt_repeats=3
    [[ "${QUICK:-0}" == "1" ]] && mqtt_repeats=1
    cblrs bench mqtt --repeats "$mqtt_repeats" --markdown > "$results/bench_mqtt.md"
    # Capture -> tracks at a subscriber, 20 cameras x 10 fps, with and without TCP_NODELAY.
    {
        cblrs bench mqtt --cameras 20 --fps 10 --runs matcher/paced \
            --repeats "$mqtt_repeats" --paced-seconds 30 --markdown
        echo
        cblrs bench mqtt --cameras 20 --fps 10 --runs matcher/paced \
            --repeats "$mqtt_repeats" --paced-seconds 30 --nagle --markdown
    } > "$results/bench_mqtt_nagle.md"
fi

echo "== backbones: Mosquitto, NATS, NATS R3 (about 8 minutes)" >&2
if command -v mosquitto_pub > /dev/null && python -c "import nats" 2> /dev/null; then
    backbone_repeats=3
    [[ "${QUICK:-0}" == "1" ]] && backbone_repeats=1
    cblrs bench backbone --repeats "$backbone_repeats" --out "$results" --quiet > /dev/null
fi

echo "== unsynchronised cameras: clock offsets, frame rates, lost messages (about 10 minutes)" >&2
async_seeds="0,1,2"
[[ "${QUICK:-0}" == "1" ]] && async_seeds="0"
async_services=""
command -v mosquitto > /dev/null || async_services="--in-process-only"
# shellcheck disable=SC2086
cblrs bench asynchrony --seeds "$async_seeds" $async_services --out "$results" --quiet > /dev/null

echo "== demo pictures" >&2
demo=$(mktemp -d)
cblrs demo --out "$demo" --quiet --json > "$results/demo_metrics.json"
python - "$demo" "$figures" <<'PY'
import sys
from pathlib import Path

import cv2

demo, figures = Path(sys.argv[1]), Path(sys.argv[2])
# README.md and docs/getting-started.md show the demo's own pictures, scaled down to keep
# the repository small.
for source, target, width in [
    ("plaza/trajectories.png", "demo_plaza_trajectories.png", 1400),
    ("roundabout/trajectories.png", "demo_roundabout_trajectories.png", 1400),
    ("plaza/overlay_NE.png", "demo_plaza_overlay_NE.png", 900),
]:
    image = cv2.imread(str(demo / source), cv2.IMREAD_COLOR)
    scale = width / image.shape[1]
    if scale < 1:
        image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(figures / target), image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
PY
rm -rf "$demo"
python - "$results/demo_metrics.json" > "$results/demo_metrics.md" <<'PY'
import json
import sys

report = json.load(open(sys.argv[1]))
keys = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1")
print("| scene | matcher | " + " | ".join(keys) + " | predicted ids / true ids |")
print("|---|---|" + "---|" * len(keys) + "---|")
for name, scene in report["scenes"].items():
    for matcher, metrics in scene["metrics"].items():
        values = " | ".join(f"{metrics[key]:.2f}" for key in keys)
        ids = f"{scene['predicted_ids'][matcher]} / {scene['ground_truth_ids']}"
        print(f"| {name} | {matcher} | {values} | {ids} |")
print()
print(f"{report['seconds']:.1f} s in all (`cblrs demo --json`).")
PY

# One markdown page with every table, in the order the documentation shows them.
{
    echo "# cblrs: measured results"
    echo
    echo "Generated by \`scripts/make_docs.sh\` on $(date -u +%Y-%m-%d). Figures: \`docs/figures/\`."
    for name in demo_metrics wildtrack_tracking bench_detect bench_camera bench_lookup bench_render \
        bench_claims bench_tracker bench_pipeline bench_track experiment_targeting experiment_resolution \
        experiment_calibration experiment_counts experiment_planes pseudo_tracking experiment_pseudo bench_analytics bench_dashboard bench_mqtt \
        bench_mqtt_nagle \
        bench_backbone bench_asynchrony; do
        if [[ -f "$results/$name.md" ]]; then
            echo
            cat "$results/$name.md"
        fi
    done
} > "$results/RESULTS.md"

# Copy the tables into README.md and the pages under docs/ between their
# "BEGIN/END generated: NAME" markers (the pages build into the MkDocs site, mkdocs.yml).
python scripts/fill_docs.py

ls -l "$figures"/*.png >&2
echo "wrote $results/RESULTS.md" >&2
