"""How right are the counts? Analytics on tracked positions against the same on ground truth.

For each scene (WILDTRACK, the synthetic plaza, roundabout and roundabout with traffic), its
checked-in site file (``sites/<scene>.yaml``) gives the places; the ground truth's analytics
are the truth and each matcher's tracks — with exact boxes and with the simulated detector
(several seeds) — are compared with it:

* **line error** = sum over lines, directions and classes of |predicted - true|, divided by
  the sum of the true counts (so over- and under-counts do not cancel);
* **entry error** = the same over zones' entries (tracks that crossed into the zone);
* **dwell error** = mean over zones of |predicted - true| / true mean dwell per visit;
* **OD error** = the same sum-of-absolute-differences ratio over the cells of the
  origin-destination matrix (the roundabout with traffic; its truth is also checked against
  the matrix the world was built with).

The analytics settings are the defaults for every scene; the site files only set a wider
hysteresis for vehicle places. Nothing here is tuned to a scene.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.analytics.config import AnalyticsConfig, HeatmapGrid
from cblrs.analytics.site import SitePlaces, load_site_places, site_extent
from cblrs.analytics.tables import AnalyticsResult, analyse_tracks
from cblrs.datasets import simulate_detections
from cblrs.datasets.scene import Scene
from cblrs.datasets.traffic import make_traffic_scene, roundabout_traffic_world, traffic_od
from cblrs.errors import DatasetError
from cblrs.experiments.resolution import load_named_scene
from cblrs.pipeline import render_scene_references, track_scene
from cblrs.places import Places
from cblrs.viz.analytics import plot_counts_over_time, plot_heatmap, plot_od, plot_site

logger = logging.getLogger(__name__)

SCENES = ("wildtrack", "plaza", "roundabout", "roundabout-traffic")


@dataclass(frozen=True)
class CountsSetup:
    """What :func:`run_counts` measures.

    Attributes:
        scenes: scene names (see :data:`SCENES`).
        matchers: matcher names.
        seeds: seeds of the simulated detector (one run per seed).
        drop, jitter: the simulated detector (``--drop`` / ``--jitter`` of ``cblrs track``).
        sites: folder with ``<scene>.yaml`` site files.
        wildtrack: WILDTRACK folder (None: found automatically).
        config: analytics settings.
    """

    scenes: tuple[str, ...] = SCENES
    matchers: tuple[str, ...] = ("fusion", "paper")
    seeds: tuple[int, ...] = (1, 2, 3)
    drop: float = 0.2
    jitter: float = 0.05
    sites: Path | None = None
    wildtrack: Path | None = None
    config: AnalyticsConfig = field(default_factory=AnalyticsConfig)


def find_sites(path: str | Path | None = None) -> Path:
    """The folder of the checked-in site files: ``path``, ``./sites`` or the repository's."""
    candidates = [Path(path)] if path is not None else [
        Path("sites"), Path(__file__).resolve().parents[3] / "sites",
    ]
    for candidate in candidates:
        if (candidate / "wildtrack.yaml").exists() or (candidate / "plaza.yaml").exists():
            return candidate
    raise DatasetError(
        f"no site files in {candidates[0]}; run from the repository or pass --sites DIR."
    )


def load_counts_scene(name: str, wildtrack: str | Path | None = None) -> Scene:
    """A scene by name: ``wildtrack`` (the data folder) or a synthetic one."""
    if name == "roundabout-traffic":

        return make_traffic_scene()
    if name in ("wildtrack", "plaza", "roundabout"):

        return load_named_scene(name, wildtrack, None)
    raise DatasetError(f"unknown scene {name!r}; known: {', '.join(SCENES)}.")


def relative_error(predicted: list[int], truth: list[int]) -> float:
    """sum |predicted - true| / sum true (NaN when there is nothing to count)."""
    total = sum(truth)
    if total == 0:
        return math.nan
    return sum(abs(p - t) for p, t in zip(predicted, truth, strict=True)) / total


def match_crossings(
    truth: AnalyticsResult, predicted: AnalyticsResult, max_seconds: float = 2.0,
    max_metres: float = 2.0,
) -> tuple[int, int, int]:
    """One-to-one matching of crossing events: same line and direction, within
    ``max_seconds`` and ``max_metres`` (Hungarian on the sum of both, normalised).

    A count can be right while its events are not (a miss and an extra cancel in the same
    line and direction); this tells them apart.

    Returns:
        ``(matched, missed, extra)``.
    """
    # lazy: scipy.optimize takes ~0.3 s to import; only this path needs it
    from scipy.optimize import linear_sum_assignment

    matched = 0
    groups = {(event.line, event.direction) for event in truth.crossings + predicted.crossings}
    for line, direction in groups:
        true = [e for e in truth.crossings if (e.line, e.direction) == (line, direction)]
        found = [e for e in predicted.crossings if (e.line, e.direction) == (line, direction)]
        if not true or not found:
            continue
        seconds = np.abs(np.subtract.outer([e.timestamp for e in true],
                                           [e.timestamp for e in found]))
        metres = np.linalg.norm(np.array([e.world_xy for e in true])[:, None]
                                - np.array([e.world_xy for e in found])[None], axis=2)
        cost = seconds / max_seconds + metres / max_metres
        cost[(seconds > max_seconds) | (metres > max_metres)] = 1e6
        rows, columns = linear_sum_assignment(cost)
        matched += int(np.count_nonzero(cost[rows, columns] < 1e6))
    return matched, len(truth.crossings) - matched, len(predicted.crossings) - matched


def count_errors(truth: AnalyticsResult, predicted: AnalyticsResult) -> dict[str, Any]:
    """Per-place counts and the summary errors of ``predicted`` against ``truth``."""
    lines = []
    keys = sorted({(row["line"], row["direction"], row["class"]) for row in truth.lines
                   + predicted.lines if row["class"] != "all"})
    for line, direction, class_label in keys:
        lines.append({"line": line, "direction": direction, "class": class_label,
                      "true": truth.line_count(line, direction, class_label),
                      "predicted": predicted.line_count(line, direction, class_label)})
    zones = []
    dwell_errors = []
    for row in truth.zones:
        other = predicted.zone_row(row["zone"])
        zones.append({"zone": row["zone"], "true_entries": row["entries"],
                      "predicted_entries": other["entries"], "true_visits": row["visits"],
                      "predicted_visits": other["visits"],
                      "true_mean_dwell_s": row["mean_dwell_s"],
                      "predicted_mean_dwell_s": other["mean_dwell_s"]})
        if row["visits"] and math.isfinite(row["mean_dwell_s"]) and row["mean_dwell_s"] > 0:
            predicted_dwell = other["mean_dwell_s"] if other["visits"] else 0.0
            dwell_errors.append(abs(predicted_dwell - row["mean_dwell_s"]) / row["mean_dwell_s"])
    od_truth = [truth.od[o][d] for o in truth.od for d in truth.od[o]]
    od_predicted = [predicted.od[o][d] for o in truth.od for d in truth.od[o]]
    matched, missed, extra = match_crossings(truth, predicted)
    return {
        "matched_crossings": matched,
        "missed_crossings": missed,
        "extra_crossings": extra,
        "lines": lines,
        "zones": zones,
        "line_error": relative_error([row["predicted"] for row in lines],
                                     [row["true"] for row in lines]),
        "entry_error": relative_error([row["predicted_entries"] for row in zones],
                                      [row["true_entries"] for row in zones]),
        "dwell_error": float(np.mean(dwell_errors)) if dwell_errors else math.nan,
        "od_error": relative_error(od_predicted, od_truth) if any(od_truth) else math.nan,
        "true_crossings": sum(row["true"] for row in lines),
        "predicted_crossings": sum(row["predicted"] for row in lines),
    }


NAIVE = AnalyticsConfig(
    line_hysteresis_m=0.0, zone_hysteresis_m=0.0, merge_gap_s=0.0, min_track_s=0.0,
    max_person_speed_m_s=1e9, max_speed_m_s=1e9,
)
"""Counting without the robustness rules: any sign change is a crossing, every border
flicker a visit, every id counts, jumps are movement."""


def without_hysteresis(places: Places) -> Places:
    """The places with their own hysteresis settings removed (for :data:`NAIVE`)."""
    return Places(
        tuple(replace(zone, hysteresis_m=None) for zone in places.zones),
        tuple(replace(line, hysteresis_m=None) for line in places.lines),
    )


def run_counts(
    setup: CountsSetup, report: Callable[[str], None] | None = None
) -> dict[str, Any]:
    """Track every scene with every matcher and detector, and compare the counts.

    Returns:
        ``{"setup": ..., "scenes": {scene: {"truth": ..., "runs": [...]}}}`` (JSON-ready).
    """

    sites = find_sites(setup.sites)
    result: dict[str, Any] = {
        "setup": {"scenes": list(setup.scenes), "matchers": list(setup.matchers),
                  "seeds": list(setup.seeds), "drop": setup.drop, "jitter": setup.jitter,
                  "settings": setup.config.to_dict(), "sites": str(sites)},
        "scenes": {},
    }
    for name in setup.scenes:
        site = load_site_places(sites / f"{name}.yaml")
        scene = load_counts_scene(name, setup.wildtrack)
        truth = analyse_tracks(scene.ground_truth, site.places, setup.config)
        naive_places = without_hysteresis(site.places)
        naive_truth = analyse_tracks(scene.ground_truth, naive_places, NAIVE)
        entry: dict[str, Any] = {
            "site": site.source, "frames": len(scene.frames),
            "seconds": float(scene.timestamps[-1] - scene.timestamps[0]),
            "true_ids": len(np.unique(scene.ground_truth.track_id)),
            "truth": {"lines": truth.lines, "zones": truth.zones, "od": truth.od},
            "runs": [],
        }
        if name == "roundabout-traffic":
            entry["built_od_matches_truth"] = _built_od_matches(truth)
        references = render_scene_references(scene)
        detectors: list[tuple[str, Scene]] = [("exact", scene)]
        for seed in setup.seeds:
            label = f"--drop {setup.drop:g} --jitter {setup.jitter:g} --seed {seed}"
            detectors.append((label, simulate_detections(
                scene, drop=setup.drop, jitter=setup.jitter, seed=seed)))
        for matcher in setup.matchers:
            for label, variant in detectors:
                start = time.perf_counter()
                tracks = track_scene(variant, matcher, references=references).tracks
                predicted = analyse_tracks(tracks, site.places, setup.config)
                errors = count_errors(truth, predicted)
                errors.update(matcher=matcher, detector=label,
                              predicted_ids=len(np.unique(tracks.track_id)),
                              seconds=time.perf_counter() - start)
                naive = count_errors(naive_truth, analyse_tracks(tracks, naive_places, NAIVE))
                errors["naive"] = {key: naive[key] for key in (
                    "line_error", "entry_error", "dwell_error", "od_error", "true_crossings",
                    "predicted_crossings")}
                entry["runs"].append(errors)
                if report is not None:
                    report(f"{name} {matcher} {label}: line error {errors['line_error']:.3f}")
        result["scenes"][name] = entry
    return result


def _built_od_matches(truth: AnalyticsResult) -> bool:
    """The ground truth's OD equals the matrix the traffic world was built with."""

    built = traffic_od(roundabout_traffic_world())
    return all(
        truth.od[f"{origin}_arm"][f"{destination}_arm"] == built.get((origin, destination), 0)
        for origin in ("east", "north", "west", "south")
        for destination in ("east", "north", "west", "south")
    )


def _percent(value: float) -> str:
    return "–" if not math.isfinite(value) else f"{100 * value:.1f} %"


def counts_report(result: dict[str, Any]) -> str:
    """Markdown tables of :func:`run_counts`' result."""
    setup = result["setup"]
    settings = setup["settings"]
    text = [
        "### How right are the counts (analytics on tracks vs on ground truth)",
        "",
        f"Places: `{setup['sites']}/<scene>.yaml`. Settings (defaults, the same for every "
        f"scene): line and zone hysteresis {settings['line_hysteresis_m']:g} m (vehicle places "
        f"1 m, set in their site files), visits merged across exits shorter than "
        f"{settings['merge_gap_s']:g} s, tracks lost after {settings['lost_after_s']:g} s, "
        f"events only from tracks that lived {settings['min_track_s']:g} s. Errors: "
        "sum of |predicted - true| over lines x directions x classes (zones' entries; OD "
        "cells) / sum of true; dwell: mean over zones of |predicted - true| / true mean "
        "dwell per visit. Missed / extra events: crossings of the truth and of the tracks "
        "that find no partner on the same line and direction within 2 s and 2 m (a miss and "
        "an extra in one line cancel in its count). Command: `cblrs experiment counts`.",
        "",
        "| scene | matcher | detector | crossings pred / true | line error | missed / extra "
        "events | entry error | dwell error | OD error | ids pred / true |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, entry in result["scenes"].items():
        for run in entry["runs"]:
            text.append(
                f"| {name} | {run['matcher']} | {run['detector']} | "
                f"{run['predicted_crossings']} / {run['true_crossings']} | "
                f"{_percent(run['line_error'])} | "
                f"{run['missed_crossings']} / {run['extra_crossings']} | "
                f"{_percent(run['entry_error'])} | "
                f"{_percent(run['dwell_error'])} | {_percent(run['od_error'])} | "
                f"{run['predicted_ids']} / {entry['true_ids']} |"
            )
    text += [
        "",
        "Without the robustness rules (no hysteresis, no merging of visits, no confirmation, "
        "jumps taken as movement; truth counted the same way), the same tracks give:",
        "",
        "| scene | matcher | detector | crossings pred / true | line error | entry error | "
        "dwell error | OD error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, entry in result["scenes"].items():
        for run in entry["runs"]:
            naive = run["naive"]
            text.append(
                f"| {name} | {run['matcher']} | {run['detector']} | "
                f"{naive['predicted_crossings']} / {naive['true_crossings']} | "
                f"{_percent(naive['line_error'])} | {_percent(naive['entry_error'])} | "
                f"{_percent(naive['dwell_error'])} | {_percent(naive['od_error'])} |"
            )
    for name, entry in result["scenes"].items():
        runs = [run for run in entry["runs"] if run["matcher"] == "fusion"]
        if not runs:
            continue
        noisy = [run for run in runs if run["detector"] != "exact"]
        exact = next((run for run in runs if run["detector"] == "exact"), None)
        text += ["", f"#### {name}: per line and direction (fusion)", "",
                 "| line | direction | class | true | exact boxes | simulated detector, "
                 "per seed |", "|---|---|---|---|---|---|"]
        for index, row in enumerate((exact or runs[0])["lines"]):
            seeds = ", ".join(str(run["lines"][index]["predicted"]) for run in noisy)
            text.append(f"| {row['line']} | {row['direction']} | {row['class']} | {row['true']} "
                        f"| {row['predicted'] if exact else '–'} | {seeds or '–'} |")
        if entry["truth"]["zones"]:
            text += ["", "| zone | true entries | exact | detector, per seed | true mean dwell s "
                     "| exact | detector, per seed |", "|---|---|---|---|---|---|---|"]
            for index, row in enumerate((exact or runs[0])["zones"]):
                seeds = ", ".join(str(run["zones"][index]["predicted_entries"]) for run in noisy)
                dwell = ", ".join(f"{run['zones'][index]['predicted_mean_dwell_s']:.1f}"
                                  for run in noisy)
                text.append(
                    f"| {row['zone']} | {row['true_entries']} | "
                    f"{row['predicted_entries'] if exact else '–'} | {seeds or '–'} | "
                    f"{row['true_mean_dwell_s']:.1f} | "
                    f"{row['predicted_mean_dwell_s']:.1f} | {dwell or '–'} |"
                )
        if "built_od_matches_truth" in entry:
            text += ["", "Ground-truth OD equals the matrix the world was built with: "
                     f"{'yes' if entry['built_od_matches_truth'] else 'NO'}."]
    return "\n".join(text)


def site_for(scene: str, sites: Path | None = None) -> SitePlaces:
    """The checked-in site file of a scene."""
    return load_site_places(find_sites(sites) / f"{scene}.yaml")


def plot_counts(result: dict[str, Any], setup: CountsSetup, folder: str | Path) -> list[Path]:
    """Figures for the docs: WILDTRACK places, heatmap and counts over time (fusion, exact
    boxes), the roundabout's OD (truth | fusion), and the line errors of every run."""

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []

    def save(figure: Any, name: str) -> None:
        path = folder / name
        figure.savefig(path, dpi=100)
        written.append(path)

    if "wildtrack" in result["scenes"]:
        site = site_for("wildtrack", setup.sites)
        scene = load_counts_scene("wildtrack", setup.wildtrack)
        save(plot_site(site.places, scene.ground_truth,
                       "WILDTRACK ground truth and sites/wildtrack.yaml"),
             "analytics_wildtrack_places.png")
        grid = HeatmapGrid.covering(site_extent(site), 0.5)
        config = replace(setup.config, heatmap=grid, interval_s=5.0)
        tracks = track_scene(scene, "fusion").tracks
        tables = analyse_tracks(tracks, site.places, config)
        save(plot_heatmap(tables, grid, site.places), "analytics_wildtrack_heatmap.png")
        save(plot_counts_over_time(tables), "analytics_wildtrack_counts.png")
    if "roundabout-traffic" in result["scenes"]:
        # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        site = site_for("roundabout-traffic", setup.sites)
        scene = load_counts_scene("roundabout-traffic")
        figure = Figure(figsize=(13.0, 5.2), layout="constrained")
        FigureCanvasAgg(figure)
        left, right = figure.subplots(1, 2)
        plot_od(analyse_tracks(scene.ground_truth, site.places, setup.config), ax=left)
        left.set_title("ground truth (entry arm -> exit arm)")
        tracked = track_scene(scene, "fusion").tracks
        plot_od(analyse_tracks(tracked, site.places, setup.config), ax=right)
        right.set_title("fusion, exact boxes")
        save(figure, "analytics_roundabout_od.png")
    save(_plot_errors(result), "analytics_count_errors.png")
    return written


def _plot_errors(result: dict[str, Any]) -> Any:
    # lazy: matplotlib takes ~0.4 s to import; only the plotting path needs it
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(9.0, 4.0), layout="constrained")
    FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    labels, exact, noisy, noisy_spread = [], [], [], []
    for name, entry in result["scenes"].items():
        for matcher in dict.fromkeys(run["matcher"] for run in entry["runs"]):
            runs = [run for run in entry["runs"] if run["matcher"] == matcher]
            labels.append(f"{name}\n{matcher}")
            exact.append(100 * next((r["line_error"] for r in runs if r["detector"] == "exact"),
                                    math.nan))
            values = [100 * r["line_error"] for r in runs if r["detector"] != "exact"]
            noisy.append(float(np.mean(values)) if values else math.nan)
            noisy_spread.append((float(np.mean(values) - np.min(values)),
                                 float(np.max(values) - np.mean(values))) if values else (0, 0))
    positions = np.arange(len(labels))
    ax.bar(positions - 0.2, exact, 0.4, label="exact boxes")
    ax.bar(positions + 0.2, noisy, 0.4, yerr=np.array(noisy_spread).T.reshape(2, -1),
           label="simulated detector (mean, min-max over seeds)", capsize=3)
    ax.axhline(2, color="0.3", linestyle=":", linewidth=1)
    ax.axhline(5, color="0.3", linestyle="--", linewidth=1)
    ax.set_xticks(positions, labels, fontsize=7)
    ax.set_yscale("symlog", linthresh=10, linscale=2)
    ax.set_ylim(0, 120)
    ax.set_yticks([0, 1, 2, 5, 10, 20, 50, 100], ["0", "1", "2", "5", "10", "20", "50", "100"])
    for x, value in [*zip(positions - 0.2, exact, strict=True),
                     *zip(positions + 0.2, noisy, strict=True)]:
        if math.isfinite(value):
            ax.text(x, value, f"{value:.1f}", ha="center", va="bottom", fontsize=6)
    ax.set_ylabel("line-count error (%)")
    ax.set_title("line-count error against ground truth (targets 2 % exact, 5 % detector)")
    ax.legend(fontsize=8)
    ax.grid(True, axis="y", linewidth=0.3)
    return figure
