"""``cblrs demo``: the whole method on a synthetic world (or a real data set), with pictures.

For each scene: render the cameras' colour reference images, turn every frame's boxes into
camera messages (colours only), track with both matchers (``paper`` and ``fusion``), score
them against the ground truth and write::

    DIR/metrics.json                       all scenes: matcher -> HOTA, DetA, AssA, ... (%)
    DIR/<scene>/metrics.json               this scene's scores and counts
    DIR/<scene>/trajectories.png           bird's-eye view: paper | fusion | ground truth
    DIR/<scene>/overlay_<camera>.png       per camera: reference colours, boxes, targets
    DIR/<scene>/references/<camera>.png    the reference images (16-bit PNG, reloadable)
    DIR/<scene>/tracks_<matcher>.txt       tracks in AI City 2024 format
    DIR/<scene>/ground_truth.txt           ground truth in the same format

The synthetic scenes are the presets of :mod:`cblrs.datasets.synthetic`: ``roundabout``
(one car handed over between two cameras twice) and ``plaza`` (four cameras, a crowd).

On a real data set with ``--detector onnx --model M.onnx`` the boxes come from the model run
on the data set's images (``Image_subsets/C<k>/``), and the overlays are drawn over the real
frames: detector boxes labelled with the fusion track they fed, the located targets, the
annotated positions (green rings) and, faintly, the reference's metric grid.

On a terminal, the synthetic demo then goes live: the plaza's cameras replayed through
``cblrs up`` (broker, matcher, dashboard, cameras) until Ctrl-C (:mod:`cblrs.cli.demo_live`).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cblrs.calibration import default_ground
from cblrs.cli.common import (
    InputError,
    UsageError,
    add_output_options,
    format_table,
    parse_frame_range,
    print_json,
    progress,
)
from cblrs.cli.demo_live import add_live_options, run_live, wants_live
from cblrs.cli.detector_options import (
    DETECTIONS_HELP,
    add_detector_options,
    detection_source,
    drop_hidden_feet,
    real_detections,
)
from cblrs.datasets.scene import Scene
from cblrs.detections import Tracks
from cblrs.reference import ReferenceImage

logger = logging.getLogger(__name__)

MATCHERS = ("paper", "fusion")
PRESET_CHOICES = ("all", "roundabout", "plaza")
DEFAULT_OUT = "cblrs-demo"
SCORE_KEYS = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "IDF1")
# A detection is labelled with the fusion track nearest to its located point within this.
_LABEL_RADIUS_M = 1.5
_SOLID_COLOURS = {"person": (214, 182, 150), "car": (150, 170, 205)}


@dataclass
class SceneReport:
    """What the demo produced for one scene."""

    name: str
    directory: Path
    cameras: int
    frames: int
    detections: int
    ground_truth_ids: int
    targeting: str = "box"
    detector: dict[str, Any] | None = None
    scores: dict[str, dict[str, float]] = field(default_factory=dict)
    predicted_ids: dict[str, int] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scene": self.name,
            "directory": str(self.directory),
            "cameras": self.cameras,
            "frames": self.frames,
            "detections": self.detections,
            "ground_truth_ids": self.ground_truth_ids,
            "targeting": self.targeting,
            **({"detector": self.detector} if self.detector is not None else {}),
            "metrics": self.scores,
            "predicted_ids": self.predicted_ids,
            "seconds": {key: round(value, 3) for key, value in self.seconds.items()},
            "files": [str(path) for path in self.files],
        }


# ---------------------------------------------------------------------------- CLI


def register(subparsers: Any) -> None:
    """Add the ``cblrs demo`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "demo",
        help="run the whole method on a built-in synthetic world and draw the results",
        description=(
            "Generate a synthetic scene (or read a WILDTRACK/MultiviewX folder), render the "
            "colour reference images, track with both matchers (paper, fusion), evaluate, "
            "and write metrics.json, a bird's-eye trajectory plot, per-camera overlays, the "
            "reference PNGs and the tracks in AI City format."
        ),
    )
    parser.add_argument(
        "--out",
        default=DEFAULT_OUT,
        metavar="DIR",
        help=f"output folder (default: ./{DEFAULT_OUT})",
    )
    parser.add_argument(
        "--preset",
        choices=PRESET_CHOICES,
        default="all",
        help="synthetic scene(s) to run (default: all = roundabout and plaza)",
    )
    parser.add_argument(
        "--dataset",
        metavar="DIR",
        help="a WILDTRACK or MultiviewX folder to run on instead of the synthetic world",
    )
    parser.add_argument(
        "--frames",
        metavar="FIRST:LAST",
        help="only these native frame numbers (inclusive), e.g. 0:995",
    )
    parser.add_argument(
        "--duration",
        type=float,
        metavar="SECONDS",
        help="length of the synthetic scenes (default: each preset's own)",
    )
    parser.add_argument(
        "--site",
        metavar="SITE",
        help="with --dataset: the cameras' geometry, positions and planes from a site file",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the synthetic world")
    parser.add_argument(
        "--targeting",
        choices=("box", "geometric"),
        default="box",
        help="where in each box the camera looks: fixed per-class position (box, default) "
        "or fitted from the calibration and a class size prior (geometric)",
    )
    add_detector_options(parser, detections_help=DETECTIONS_HELP)
    add_live_options(parser)
    add_output_options(parser)
    parser.set_defaults(handler=run)


def run(args: Any) -> int:
    """Run ``cblrs demo`` with its parsed arguments; the exit code."""
    if args.duration is not None and not args.duration > 0:
        raise UsageError(f"--duration must be a positive number of seconds, got {args.duration}.")
    frame_range = parse_frame_range(args.frames) if args.frames else None
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise InputError(f"cannot create the output folder {out}: {error.strerror}.") from None
    source = detection_source(args)
    live = wants_live(args)
    live_scene = None
    if source != "annotations" and not args.dataset:
        raise UsageError("--detector and --detections need --dataset DIR (a real data set).")
    start = time.perf_counter()
    reports = []
    if args.site and not args.dataset:
        raise UsageError(
            "--site needs --dataset (the synthetic scenes bring their own cameras)."
        )
    if args.dataset:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.datasets import load_scene
        from cblrs.pipeline import render_scene_references

        scene = load_scene(args.dataset)
        if frame_range:
            scene = scene.select_frames(*frame_range)
        site_options: dict[str, Any] = {}
        if args.site:
            # lazy: a subcommand imports the library when it runs, so its --help starts fast
            from cblrs.site import load_site

            site = load_site(args.site)
            scene = site.scene(scene)
            references = [site.render_reference(n) for n in scene.camera_names]
            positions = site.camera_positions()
            site_options["camera_positions"] = {
                name: positions[name] for name in scene.camera_names if name in positions
            }
        else:
            references = render_scene_references(scene)
        scene, detector_summary = real_detections(args, scene, references, source, args.quiet)
        images = None
        if source == "detector":
            # lazy: a subcommand imports the library when it runs, so its --help starts fast
            from cblrs.datasets.images import scene_image_paths

            images = scene_image_paths(args.dataset, len(scene.cameras), scene.frames)
        reports.append(
            run_scene(
                scene, out / scene.name, quiet=args.quiet, targeting=args.targeting,
                references=references, drop_hidden_feet=drop_hidden_feet(args, source),
                images=images, detector=detector_summary, area=default_ground(args.dataset),
                **site_options,
            )
        )
    else:
        presets = ["roundabout", "plaza"] if args.preset == "all" else [args.preset]
        for preset in presets:
            scene, world = synthetic_scene(preset, args.seed, args.duration)
            if preset == "plaza" and not frame_range:
                live_scene = scene
            if frame_range:
                scene = scene.select_frames(*frame_range)
            reports.append(
                run_scene(
                    scene, out / preset, world=world, quiet=args.quiet, targeting=args.targeting
                )
            )
    summary = {report.name: report.to_dict() for report in reports}
    metrics_path = out / "metrics.json"
    metrics_path.write_text(
        json.dumps({name: item["metrics"] for name, item in summary.items()}, indent=2) + "\n"
    )
    elapsed = time.perf_counter() - start
    if args.json:
        print_json({"out": str(out), "seconds": round(elapsed, 3), "scenes": summary})
        return 0
    print(results_table(reports))
    print()
    for report in reports:
        notes = scene_notes(report)
        if notes:
            print(notes)
    print(f"Wrote {sum(len(r.files) for r in reports) + 1} files to {out}/ in {elapsed:.1f} s:")
    print(f"  {metrics_path}")
    for report in reports:
        pictures = [p for p in report.files if p.suffix == ".png" and p.parent == report.directory]
        for path in pictures:
            print(f"  {path}")
        print(f"  {report.directory}/references/*.png, tracks_*.txt, ground_truth.txt")
    if not live:
        return 0
    if live_scene is None:  # the live site replays the plaza, also after --preset roundabout
        live_scene, _ = synthetic_scene("plaza", args.seed)
    return run_live(args, out, live_scene)


def results_table(reports: list[SceneReport]) -> str:
    """The printed table: one row per scene and matcher."""
    rows = []
    for report in reports:
        for matcher in MATCHERS:
            scores = report.scores[matcher]
            rows.append(
                [report.name, matcher]
                + [f"{scores[key]:.1f}" for key in SCORE_KEYS]
                + [f"{report.predicted_ids[matcher]} / {report.ground_truth_ids}"]
            )
    headers = ["scene", "matcher", *SCORE_KEYS, "ids (pred / true)"]
    return format_table(headers, rows)


def scene_notes(report: SceneReport) -> str:
    """One line per scene saying what it shows."""
    return (
        f"{report.name}: {report.cameras} cameras, {report.frames} frames, "
        f"{report.detections} detections, {report.ground_truth_ids} true "
        + ("identity." if report.ground_truth_ids == 1 else "identities.")
    )


# ---------------------------------------------------------------------------- work


def synthetic_scene(preset: str, seed: int = 0, duration_s: float | None = None):
    """The scene and the world spec of a synthetic preset."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.datasets.presets import make_world
    from cblrs.datasets.synthetic import SyntheticWorld

    world = make_world(preset, seed=seed, duration_s=duration_s)
    return SyntheticWorld(world).scene(), world


def run_scene(
    scene: Scene,
    directory: Path,
    world: Any = None,
    quiet: bool = False,
    targeting: str = "box",
    references: list[ReferenceImage] | None = None,
    camera_positions: dict[str, Any] | None = None,
    drop_hidden_feet: bool = False,
    images: list[list[Path]] | None = None,
    detector: dict[str, Any] | None = None,
    area: tuple[float, float, float, float] | None = None,
) -> SceneReport:
    """Render, track with both matchers, evaluate and draw one scene into ``directory``.

    Args:
        scene: the scene.
        directory: output folder (created).
        world: the :class:`cblrs.datasets.synthetic.WorldSpec` of a synthetic scene, used to
            draw its 3D boxes in the overlays; None for real data (reference colours only).
        quiet: no progress bars.
        targeting: ``"box"`` or ``"geometric"`` (see :func:`cblrs.pipeline.track_scene`).
        references: the cameras' reference images (default: rendered for the scene's plane).
        camera_positions: the fusion tracker's camera positions (default: the posed
            cameras' centres).
        drop_hidden_feet: see :func:`cblrs.pipeline.track_scene` (for a detector's boxes).
        images: ``images[f][c]`` the camera frames the detections came from; the overlays
            are drawn over them.
        detector: what the detector did (model, tiles, timings), kept in metrics.json.
        area: the annotated ground area, for scoring (see :func:`cblrs.evaluate`).
    """
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.datasets.aicity import write_tracks
    from cblrs.evaluation.metrics import evaluate
    from cblrs.pipeline import render_scene_references, scene_targeters, track_scene

    directory.mkdir(parents=True, exist_ok=True)
    (directory / "references").mkdir(exist_ok=True)
    truth = scene.ground_truth
    report = SceneReport(
        name=scene.name,
        directory=directory,
        cameras=len(scene.cameras),
        frames=len(scene.frames),
        detections=sum(len(d) for row in scene.detections for d in row),
        ground_truth_ids=len(np.unique(truth.track_id)),
        targeting=targeting,
    )
    started = time.perf_counter()
    if references is None:
        references = render_scene_references(scene)
    report.seconds["render"] = time.perf_counter() - started
    report.detector = detector
    for reference, camera in zip(references, scene.cameras, strict=True):
        report.files.append(reference.save(directory / "references" / f"{camera.name}.png"))

    targeters = scene_targeters(scene, targeting)
    tracks: dict[str, Tracks] = {}
    for matcher in progress(MATCHERS, f"{scene.name}: matchers", quiet):
        started = time.perf_counter()
        options: dict[str, Any] = {}
        if camera_positions is not None and matcher == "fusion":
            options["camera_positions"] = camera_positions
        result = track_scene(
            scene,
            matcher,
            references=references,
            progress=not quiet,
            # Targeters are built once and shared by both matchers (geometric ones cost).
            targeting="box" if targeters is None else targeters,
            drop_hidden_feet=drop_hidden_feet,
            **options,
        )
        report.seconds[matcher] = time.perf_counter() - started
        tracks[matcher] = result.tracks
        metrics = evaluate(truth, result.tracks, area=area)
        report.scores[matcher] = {key: round(value, 3) for key, value in metrics.to_dict().items()}
        report.predicted_ids[matcher] = len(np.unique(result.tracks.track_id))
        path = directory / f"tracks_{matcher}.txt"
        write_tracks(path, result.tracks)
        report.files.append(path)
    write_tracks(directory / "ground_truth.txt", truth)
    report.files.append(directory / "ground_truth.txt")

    started = time.perf_counter()
    report.files.append(draw_trajectories(scene, tracks, directory, world, area=area))
    report.files.extend(
        draw_overlays(
            scene, references, tracks["fusion"], directory, world, targeters,
            images=images, drop_hidden_feet=drop_hidden_feet,
        )
    )
    report.seconds["pictures"] = time.perf_counter() - started

    path = directory / "metrics.json"
    path.write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    report.files.append(path)
    return report


def _plot_area(scene: Scene) -> tuple[float, float, float, float]:
    """The ground plane, widened to show the cameras standing around it."""
    plane = scene.plane
    x0, y0 = plane.origin
    x1, y1 = x0 + plane.width, y0 + plane.length
    centres = np.array([camera.centre[:2] for camera in scene.cameras if camera.has_pose])
    if len(centres):
        margin = 0.05 * max(plane.width, plane.length)
        x0, y0 = min(x0, centres[:, 0].min() - margin), min(y0, centres[:, 1].min() - margin)
        x1, y1 = max(x1, centres[:, 0].max() + margin), max(y1, centres[:, 1].max() + margin)
    return (float(x0), float(y0), float(x1), float(y1))


def draw_trajectories(
    scene: Scene,
    tracks: dict[str, Tracks],
    directory: Path,
    world: Any = None,
    area: tuple[float, float, float, float] | None = None,
) -> Path:
    """``trajectories.png``: paper | fusion | ground truth, bird's-eye view (the annotated
    ``area``, if given, shaded)."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.datasets.synthetic import GroundMarking
    from cblrs.viz.trajectories import plot_trajectories

    markings = list(world.markings) if world is not None else []
    if world is not None:
        markings += [_footprint_marking(structure) for structure in world.structures]
    if area is not None:
        x0, y0, width, length = area
        corners = ((x0, y0), (x0 + width, y0), (x0 + width, y0 + length), (x0, y0 + length))
        markings.append(GroundMarking(corners, (232, 232, 222)))
    figure = plot_trajectories(
        scene.ground_truth,
        {name: tracks[name] for name in MATCHERS},
        title=f"{scene.name}: predicted trajectories vs ground truth "
        f"({len(scene.cameras)} cameras, {scene.timestamps[-1] - scene.timestamps[0]:.0f} s)",
        cameras=scene.cameras,
        area=_plot_area(scene),
        markings=markings,
    )
    path = directory / "trajectories.png"
    figure.savefig(path, dpi=110)
    return path


def _footprint_marking(structure: Any) -> Any:
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.datasets.synthetic import GroundMarking

    corners = structure.corners()[:4, :2]
    return GroundMarking(tuple(map(tuple, corners.tolist())), (150, 150, 150))


def overlay_frame_index(scene: Scene) -> int:
    """The frame to draw: most cameras with detections, then most detections; among equals
    the middle of the first longest stretch of consecutive frames (e.g. mid hand-over)."""
    cameras_seeing = np.array([sum(len(d) > 0 for d in row) for row in scene.detections])
    totals = np.array([sum(len(d) for d in row) for row in scene.detections])
    score = cameras_seeing * 100000 + totals
    best = np.flatnonzero(score == score.max())
    runs = np.split(best, np.flatnonzero(np.diff(best) > 1) + 1)
    longest = max(runs, key=len)
    return int(longest[len(longest) // 2])


def draw_overlays(
    scene: Scene,
    references: list[ReferenceImage],
    fusion_tracks: Tracks,
    directory: Path,
    world: Any = None,
    targeters: Any = None,
    images: list[list[Path]] | None = None,
    drop_hidden_feet: bool = False,
) -> list[Path]:
    """``overlay_<camera>.png`` for one frame: reference colours, boxes labelled with the
    fusion track they fed, and each box's target (its reported location seen in the image);
    for synthetic scenes also the 3D boxes and a green ring at each true footprint centre;
    over ``images`` (the real frames), the annotated positions as green rings and the
    reference's colours and metric grid faintly.
    """
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.edge import make_message
    from cblrs.viz.overlay import camera_overlay, draw_boxes_3d, save_image, world_frame

    index = overlay_frame_index(scene)
    frame = int(scene.frames[index])
    rows = fusion_tracks.frame == frame
    track_xy, track_ids = fusion_tracks.world_xy[rows], fusion_tracks.track_id[rows]
    truth = scene.ground_truth[scene.ground_truth.frame == frame]
    corners = colours = None
    if world is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.datasets.synthetic import SyntheticWorld

        synthetic = SyntheticWorld(world)
        corners, identities = synthetic.boxes_at(synthetic.states(), index)
        classes = {item.object_id: item.class_name for item in world.objects}
        # Neutral solids per class, so the boxes' colours (fusion ids) stand out.
        solid_colours = [_SOLID_COLOURS.get(classes[int(i)], (190, 190, 190)) for i in identities]
        fixed = np.array([s.corners() for s in world.structures]).reshape(-1, 8, 3)
        corners = np.concatenate([corners, fixed])
        solid_colours += [(205, 200, 190)] * len(fixed)
        colours = np.array(solid_colours, dtype=np.float64).reshape(-1, 3)
    paths = []
    if targeters is None:
        targeters = [None] * len(scene.cameras)
    for number, (camera, reference, detections, targeter) in enumerate(zip(
        scene.cameras, references, scene.detections[index], targeters, strict=True
    )):
        message = make_message(
            camera.name, 0, 0.0, frame, detections, reference, targeter=targeter,
            drop_hidden_feet=drop_hidden_feet,
        )
        located, valid, _ = reference.planes.decode(message.colour)
        labels = np.full(len(detections), -1, dtype=np.int64)
        if len(track_xy) and valid.any():
            distance = np.linalg.norm(located[:, None, :] - track_xy[None, :, :], axis=2)
            nearest = np.argmin(np.where(np.isfinite(distance), distance, np.inf), axis=1)
            close = valid & (distance[np.arange(len(detections)), nearest] <= _LABEL_RADIUS_M)
            labels[close] = track_ids[nearest[close]]
        targets = np.full((len(detections), 2), np.nan)
        if valid.any():
            targets[valid], _ = camera.world_to_pixel(located[valid], reference.planes[0].height)
        background = None
        highlight = None
        opacity = 1.0
        if world is not None and camera.has_pose and corners is not None:
            background = draw_boxes_3d(
                world_frame(camera, world.markings), camera, corners, colours=colours
            )
            highlight, _ = camera.world_to_pixel(truth.world_xy)
        elif images is not None:
            # lazy: a subcommand imports the library when it runs, so its --help starts fast
            from cblrs.datasets.images import UnusableImage, read_image

            try:
                background = read_image(images[index][number])[..., ::-1]
                opacity = 0.35
            except UnusableImage as error:
                logger.warning("overlay of %s drawn without its frame: %s", camera.name, error)
            highlight = visible_pixels(camera, truth.world_xy)
        image = camera_overlay(
            reference,
            detections,
            targets,
            frame=background,
            identities=labels,
            grid_m=5.0 if world is not None else 1.0,
            title=f"{scene.name}  camera {camera.name}  frame {frame}",
            highlight_pixels=highlight,
            caption="labels: fusion track ids   dot: located target   grey: no location / no track"
            + ("   green ring: true position" if highlight is not None else ""),
            overlay_opacity=opacity,
        )
        paths.append(save_image(directory / f"overlay_{camera.name}.png", image))
    return paths


def visible_pixels(camera: Any, world_xy: np.ndarray) -> np.ndarray:
    """Raw pixels of ground points the camera sees (in front, inside the image before the
    lens model, which far outside the view folds points back into the image); (N, 2), NaN
    for the others."""
    homogeneous = np.column_stack([world_xy, np.ones(len(world_xy))]) @ camera.homography.T
    pixels = np.full((len(world_xy), 2), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        pinhole = homogeneous[:, :2] / homogeneous[:, 2:3]
    seen = (homogeneous[:, 2] > 0) & camera.contains(pinhole)
    if seen.any():
        pixels[seen], _ = camera.world_to_pixel(world_xy[seen])
    return pixels
