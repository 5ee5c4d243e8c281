"""What pseudo coordinates do not hide: recovering the key's transform from the database.

On WILDTRACK the matcher's database is made as in a deployment: the cameras' references are
rendered with a key (:func:`cblrs.privacy.render_pseudo_reference`), the fusion tracker tracks
the second half of the sequence (frames 500-995, 50 s; its first 10 or 25 s for the shorter
rows) and its track positions are the database. The adversary holds that database and
knows how cblrs works (a rotation and a translation); what else they know is each row:

* **nothing about the site**: the pseudo positions as they are (the error is how far they are
  from the real ones);
* **k landmarks** with a position error: k people positions the adversary pairs with their
  site position (they stood there, or saw someone there at a known time), with Gaussian error
  sigma per axis; :func:`cblrs.privacy.attack.fit_rigid`;
* **the camera masts**: the pseudo site the matcher is given holds every camera's pseudo
  position (the fusion tracker needs them); anyone who can see where the masts stand knows
  their site positions to some sigma;
* **where people walk**: a survey of the site (the ground truth of the first half, frames
  0-495, another 50 s) as a density map, or reduced to a walkable / not walkable map;
  :func:`cblrs.privacy.attack.align_to_density`.

Every row is repeated over keys (re-keying the database is exact: the tracker's output does
not depend on the key, as ``cblrs track --key`` shows to the hundredth of a HOTA point) or
over draws of landmarks and errors. The error of a trial is the median, over the database's
positions, of the distance between where the recovered transform and the key put them.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from cblrs.datasets.scene import Scene
from cblrs.pipeline import camera_positions, scene_planes, track_scene
from cblrs.privacy.attack import DensityMap, align_to_density, fit_rigid, recovery_error
from cblrs.privacy.frame import positions_to_pseudo, render_pseudo_reference
from cblrs.privacy.key import PseudoKey

logger = logging.getLogger(__name__)

SURVEY_FRAMES = (0, 495)
DATABASE_FRAMES = (500, 995)
DATABASE_SECONDS = (10, 25, 50)


@dataclass(frozen=True)
class PseudoAttackSetup:
    """Options of ``cblrs experiment pseudo``.

    Attributes:
        landmarks: numbers of landmarks k.
        sigmas_m: landmark position errors (per axis), metres.
        mast_sigmas_m: errors of the adversary's camera-mast positions, metres.
        draws: landmark draws per (k, sigma).
        keys: keys per walkway row.
        seed: random seed of the draws and keys.
    """

    landmarks: tuple[int, ...] = (2, 3, 5, 10)
    sigmas_m: tuple[float, ...] = (0.1, 0.5, 2.0)
    mast_sigmas_m: tuple[float, ...] = (0.5, 2.0)
    draws: int = 200
    keys: int = 5
    seed: int = 0


def run_pseudo_attack(scene: Scene, setup: PseudoAttackSetup) -> dict[str, Any]:
    """Track the database in pseudo mode and run every attack; JSON-ready rows."""
    started = time.perf_counter()
    rng = np.random.default_rng(setup.seed)
    key = PseudoKey(rng.bytes(32), "00000000")
    database_scene = scene.select_frames(*DATABASE_FRAMES)
    planes = scene_planes(scene)
    references = [render_pseudo_reference(camera, planes, key) for camera in scene.cameras]
    result = track_scene(
        database_scene, "fusion", references=references,
        camera_positions=positions_to_pseudo(camera_positions(scene), key),
    )
    tracks = result.tracks
    pseudo_xy = tracks.world_xy
    site_xy = key.to_site(pseudo_xy)
    seconds = (tracks.frame - DATABASE_FRAMES[0]) / scene.frames_per_second \
        if scene.frames_per_second else np.zeros(len(tracks))
    truth = scene.ground_truth
    survey = truth.world_xy[(truth.frame >= SURVEY_FRAMES[0]) & (truth.frame <= SURVEY_FRAMES[1])]
    rows: list[dict[str, Any]] = []

    def add(knowledge: str, amount: str, errors: list[float], trials: int) -> None:
        values = np.asarray(errors)
        rows.append({
            "knowledge": knowledge, "amount": amount, "trials": trials,
            "median_m": float(np.median(values)), "p90_m": float(np.quantile(values, 0.9)),
            "under_1m": float(np.mean(values < 1.0)),
        })

    add("nothing about the site", f"{len(pseudo_xy)} positions",
        [float(np.median(np.linalg.norm(pseudo_xy - site_xy, axis=1)))], 1)
    # Landmarks: people positions of the database paired with their site position.
    for sigma in setup.sigmas_m:
        for count in setup.landmarks:
            errors = []
            for _ in range(setup.draws):
                chosen = rng.choice(len(site_xy), size=count, replace=False)
                noisy = pseudo_xy[chosen] + rng.normal(0.0, sigma, (count, 2))
                recovered = fit_rigid(noisy, site_xy[chosen])
                errors.append(float(np.median(recovery_error(recovered, pseudo_xy, site_xy))))
            add(f"landmarks, error {sigma:g} m", f"k = {count}", errors, setup.draws)
    # Camera masts: exact pseudo positions (the pseudo site), site positions known to sigma.
    masts = camera_positions(scene)
    names = sorted(masts)
    site_masts = np.array([masts[name][:2] for name in names])
    pseudo_masts = np.array([positions_to_pseudo(masts, key)[name][:2] for name in names])
    for sigma in setup.mast_sigmas_m:
        errors = []
        for _ in range(setup.draws):
            guessed = site_masts + rng.normal(0.0, sigma, site_masts.shape)
            recovered = fit_rigid(pseudo_masts, guessed)
            errors.append(float(np.median(recovery_error(recovered, pseudo_xy, site_xy))))
        add(f"camera masts (from the pseudo site), error {sigma:g} m",
            f"{len(names)} cameras", errors, setup.draws)
    # Where people walk: a survey of the first half as a density, or as walkable / not.
    for walkable in (False, True):
        density = DensityMap.from_points(survey, walkable_only=walkable)
        label = ("walkable area (yes/no map from a 50 s survey)" if walkable
                 else "footfall density (a 50 s survey)")
        for duration in DATABASE_SECONDS:
            window = seconds < duration
            errors = []
            for _ in range(setup.keys):
                other = PseudoKey(rng.bytes(32), "00000001")
                moved = other.to_pseudo(site_xy[window])
                recovered, _ = align_to_density(moved, density, coarse_deg=2.0)
                errors.append(float(np.median(recovery_error(recovered, moved, site_xy[window]))))
            add(label, f"{duration} s of database ({int(window.sum())} positions)", errors,
                setup.keys)
    return {
        "dataset": scene.name,
        "database_frames": list(DATABASE_FRAMES),
        "survey_frames": list(SURVEY_FRAMES),
        "database_positions": len(pseudo_xy),
        "setup": {
            "landmarks": list(setup.landmarks), "sigmas_m": list(setup.sigmas_m),
            "mast_sigmas_m": list(setup.mast_sigmas_m), "draws": setup.draws,
            "keys": setup.keys, "seed": setup.seed,
        },
        "rows": rows,
        "seconds": time.perf_counter() - started,
    }


def pseudo_attack_report(result: dict[str, Any]) -> str:
    """The markdown table of :func:`run_pseudo_attack`."""
    setup = result["setup"]
    lines = [
        f"### Recovering the pseudo transform ({result['dataset']}: the database is the fusion "
        f"tracker's {result['database_positions']} pseudo positions of frames "
        f"{result['database_frames'][0]}-{result['database_frames'][1]})",
        "",
        "Error: per trial, the median over the database's positions of the distance between "
        "where the adversary's recovered transform and the key put them; median and 90th "
        f"percentile over trials ({setup['draws']} draws per landmark row, {setup['keys']} keys "
        f"per walkway row, seed {setup['seed']}). Command: `cblrs experiment pseudo`.",
        "",
        "| adversary knows | amount | trials | error median m | error p90 m | trials under 1 m |",
        "|---|---|---|---|---|---|",
    ]
    for row in result["rows"]:
        lines.append(
            f"| {row['knowledge']} | {row['amount']} | {row['trials']} | "
            f"{_metres(row['median_m'])} | {_metres(row['p90_m'])} | "
            f"{100 * row['under_1m']:.0f} % |"
        )
    return "\n".join(lines)


def _metres(value: float) -> str:
    return f"{value:,.0f}" if value >= 100 else f"{value:.2f}"
