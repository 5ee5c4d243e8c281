"""``cblrs camera``: an edge camera node publishing colour-located detections over MQTT."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

from cblrs.cli.backbone import (
    add_backbone_options,
    camera_transport,
    connect_or_spool,
    uses_nats,
)
from cblrs.cli.common import InputError, UsageError, add_output_options, print_json
from cblrs.cli.mqtt_options import add_mqtt_options, connect_or_queue, mqtt_settings
from cblrs.cli.stopping import Interrupted

logger = logging.getLogger(__name__)

DEFAULT_SPOOL_FOLDER = Path("~/.local/state/cblrs/spool")
SPOOL_ENVIRONMENT = "CBLRS_SPOOL_DIR"
"""Folder of the default spool files, instead of :data:`DEFAULT_SPOOL_FOLDER`."""
EXIT_UNCONFIRMED = 3
"""Exit code of ``cblrs camera`` when messages remain in its spool."""
STOP_DEADLINE_S = 15.0
"""A stopped camera ends within this long even if a library call blocks it (a stream that
stopped sending); its clean stop waits STOP_FLUSH_S (5 s) for the broker at most."""


def register(subparsers) -> None:
    """Add the ``cblrs camera`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "camera",
        help="run an edge camera node: detections -> reference colours -> MQTT",
        description=(
            "Publish one camera's detections, located through its colour reference image, on "
            "cblrs/<plane>/<camera>/detections (QoS 1). Only boxes and colours leave the "
            "camera. Recorded timestamps are mapped to wall time as EPOCH + t; give every "
            "camera of one replay the same --epoch."
        ),
    )
    parser.add_argument("--camera", required=True, help="camera id (a dataset camera name)")
    reference = parser.add_mutually_exclusive_group(required=True)
    reference.add_argument("--reference", type=Path, help="the camera's reference PNG")
    reference.add_argument(
        "--references", type=Path, help="folder of reference PNGs named <camera>.png"
    )
    reference.add_argument(
        "--site",
        type=Path,
        help="render this camera's own reference from a site file (uses only its entry and "
        "the planes)",
    )
    parser.add_argument(
        "--key", type=Path, help="with --site: render the reference in the pseudo frame of this "
        "key file (docs/privacy.md); an edge device is better given only its rendered PNG"
    )
    parser.add_argument(
        "--plane", type=int, help="plane id to publish for (default: the reference's only plane)"
    )
    source = parser.add_argument_group("source (exactly one)")
    source.add_argument("--detections", type=Path, help="detections file (MOT or AI City)")
    source.add_argument(
        "--format", choices=("mot", "aicity"), default="mot", help="detections file format"
    )
    source.add_argument(
        "--aicity-camera", type=int, help="AI City: keep rows of this camera column value"
    )
    source.add_argument("--dataset", type=Path, help="WILDTRACK or MultiviewX folder")
    source.add_argument("--video", help="video file (or a device number / URL with --live)")
    source.add_argument("--images", type=Path, help="folder of image files, in name order")
    source.add_argument("--live", action="store_true", help="video is a live feed")
    source.add_argument("--fps", type=float, help="frame rate of the frame numbering")
    source.add_argument(
        "--frame-step", type=int, help="detections files: emit every Nth frame (default: auto)"
    )
    source.add_argument(
        "--frames",
        metavar="FIRST:LAST",
        help="dataset: only these native frame numbers; video / images: only these frames "
        "(0-based; a video that ends before LAST is an error)",
    )
    source.add_argument(
        "--class", dest="class_name", default="person", help="class of file detections"
    )
    detector = parser.add_argument_group("detector (video / images)")
    detector.add_argument(
        "--detector",
        choices=("onnx", "yolo", "blob"),
        default="onnx",
        help="onnx: a YOLOX / Ultralytics YOLOv5/v8/v11 ONNX export on onnxruntime (default); "
        "yolo: Ultralytics .pt weights (pip install cblrs[yolo]); blob: a colour",
    )
    detector.add_argument(
        "--model", type=Path, help="ONNX model file (local; never downloaded)"
    )
    detector.add_argument(
        "--tiling",
        choices=("auto", "off"),
        default="auto",
        help="onnx: also detect on tiles where the reference image says people look small "
        "(default) or on the whole frame only",
    )
    detector.add_argument("--iou", type=float, default=0.45, help="onnx: NMS IoU threshold")
    detector.add_argument(
        "--layout",
        choices=("auto", "yolox", "yolov5", "yolov8"),
        default="auto",
        help="onnx: model output layout (default: from its output shape)",
    )
    detector.add_argument(
        "--hidden-feet",
        choices=("auto", "keep", "drop"),
        default="auto",
        help="boxes whose feet a nearer box hides: no location (default for detector boxes "
        "and detection files) or keep it (default for dataset annotations)",
    )
    detector.add_argument("--weights", type=Path, help="YOLO model file (local; never downloaded)")
    detector.add_argument("--confidence", type=float, default=0.25, help="minimum score")
    detector.add_argument("--device", default="cpu", help="YOLO device")
    detector.add_argument(
        "--blob-colour", default="255,0,0", metavar="R,G,B", help="blob detector colour"
    )
    detector.add_argument("--blob-tolerance", type=int, default=30)
    detector.add_argument("--blob-min-area", type=int, default=20)
    timing = parser.add_argument_group("timing")
    timing.add_argument(
        "--realtime",
        action="store_true",
        help="pace by the recorded timestamps (default for files: as fast as possible)",
    )
    timing.add_argument(
        "--speed", type=float, default=1.0,
        help="with --realtime: speed-up. Capture times are divided by it, so the matcher sees "
        "everyone move SPEED times faster and its tracks differ from the recording's (a load "
        "test); for the recording's own tracks, replay without --realtime")
    timing.add_argument(
        "--epoch",
        type=float,
        help="seconds since 1970 added to recorded timestamps (same for every camera of a replay)",
    )
    timing.add_argument(
        "--first-sequence",
        type=int,
        help="sequence number of the first message (default 0, so a repeated replay is "
        "recognised as duplicates; --live: the clock in milliseconds, so a restarted live "
        "camera is not)",
    )
    delivery = parser.add_argument_group(
        "delivery",
        "Messages wait in a spool file until the matcher confirms it stored them; a camera "
        "restarted on the same spool sends what is still there. Exit code 0: the matcher "
        "confirmed everything (with --confirm-timeout 0: the broker acknowledged "
        "everything); 3: some messages remain in the spool (sent again on the next start); "
        "1: refused by the broker, or another error.",
    )
    delivery.add_argument(
        "--spool", type=Path, metavar="FILE",
        help=f"spool file (default: ${SPOOL_ENVIRONMENT} or {DEFAULT_SPOOL_FOLDER}, file "
        "<plane>-<camera>.db)",
    )
    delivery.add_argument(
        "--spool-max-mb", type=float, default=512.0,
        help="spool size bound, MiB; when full the oldest unconfirmed messages are dropped "
        "(counted, logged) (default 512: ~9 h of a 30 fps camera)",
    )
    delivery.add_argument(
        "--flush-timeout",
        type=float,
        default=30.0,
        help="seconds to wait at the end for the broker to acknowledge everything (default 30)",
    )
    delivery.add_argument(
        "--confirm-timeout", type=float, default=10.0,
        help="then, seconds to wait for the matcher's confirmations (default 10; 0: do not "
        "wait)",
    )
    delivery.add_argument(
        "--resend-after", type=float, default=30.0,
        help="send unconfirmed messages again after this many seconds without a "
        "confirmation while a matcher is online (doubles each round; default 30)",
    )
    add_mqtt_options(parser)
    parser.add_argument(
        "--mqtt-version",
        choices=("auto", "5", "3.1.1"),
        default="auto",
        help="MQTT version: auto (5, or 3.1.1 when the broker refuses 5, as the NATS server's "
        "MQTT listener does), 5 or 3.1.1",
    )
    add_backbone_options(parser, matcher=False)
    add_output_options(parser)
    parser.set_defaults(handler=run, stop_signals=(STOP_DEADLINE_S, EXIT_UNCONFIRMED))


def load_reference(args: argparse.Namespace, expected_size: tuple[int, int] | None):
    """The camera's reference image: from ``--reference``, ``--references`` or ``--site``."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.reference import ReferenceImage

    if getattr(args, "site", None) is not None:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.site import load_site

        site = load_site(args.site)
        if site.pseudo_key_id is not None:
            raise UsageError(
                f"{args.site} is a pseudo site; give the camera its reference rendered from the "
                "real site with the key (cblrs render --site SITE --key KEY), or --site SITE "
                "--key KEY."
            )
        if getattr(args, "key", None) is None:
            reference = site.render_reference(args.camera)
        else:
            from cblrs.privacy import PseudoKey, render_pseudo_reference

            reference = render_pseudo_reference(
                site.camera(args.camera).camera, site.require_planes("a camera"),
                PseudoKey.load(args.key),
            )
        if expected_size is not None and reference.image_size != tuple(expected_size):
            raise UsageError(
                f"{args.site.name}: camera {args.camera!r} is {reference.image_size[0]}x"
                f"{reference.image_size[1]} but its frames are {expected_size[0]}x"
                f"{expected_size[1]}."
            )
        return reference
    if getattr(args, "key", None) is not None:
        raise UsageError("--key goes with --site; a --reference PNG already holds its colours.")
    if args.reference is not None:
        path = args.reference
    else:
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.cli.render import file_name

        path = args.references / f"{file_name(args.camera, 0)}.png"
    return ReferenceImage.load(path, expected_size=expected_size)


def _frames_range(text: str | None) -> tuple[int | None, int | None]:
    if not text:
        return None, None
    first, separator, last = text.partition(":")
    try:
        return (int(first) if first else None), (int(last) if separator and last else None)
    except ValueError:
        raise UsageError(f"--frames {text!r} must be FIRST:LAST frame numbers.") from None


def build_source(args: argparse.Namespace):
    """``(frames iterator, expected image size or None)`` for the chosen source."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.detections import class_id_of
    from cblrs.runtime.camera import sources

    chosen = [
        name
        for name in ("detections", "dataset", "video", "images")
        if getattr(args, name) is not None
    ]
    if len(chosen) != 1:
        raise UsageError(
            "give exactly one source: --detections, --dataset, --video or --images"
            + (f" (got {', '.join('--' + name for name in chosen)})." if chosen else ".")
        )
    try:
        class_id = class_id_of(args.class_name)
    except ValueError as error:
        raise UsageError(str(error)) from None
    kind = chosen[0]
    if kind == "dataset":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.datasets import load_scene

        scene = load_scene(args.dataset)
        first, last = _frames_range(args.frames)
        if first is not None or last is not None:
            scene = scene.select_frames(first, last)
        index = sources.camera_position(scene.camera_names, args.camera)
        if scene.camera_names[index] != args.camera:
            raise UsageError(
                f"--camera must be the dataset's camera name ({scene.camera_names[index]})."
            )
        return sources.scene_source(scene, index), scene.cameras[index].image_size
    if kind == "detections":
        if args.fps is None:
            raise UsageError("--detections needs --fps (frame rate of its frame numbers).")
        if args.format == "mot":
            frames = sources.mot_source(args.detections, args.fps, class_id, args.frame_step)
        else:
            frames = sources.aicity_source(
                args.detections, args.fps, args.aicity_camera, class_id, args.frame_step
            )
        return frames, None
    detector = build_detector(args, class_id)
    first, last = _frames_range(args.frames)
    if kind == "video":
        return sources.video_source(
            args.video, detector, args.fps, live=args.live, first=first, last=last
        ), None
    return sources.image_folder_source(
        args.images, detector, args.fps or 10.0, first=first, last=last
    ), None


def build_detector(args: argparse.Namespace, class_id: int):
    """The detector ``--detector`` names (onnx, yolo or blob), built from its options."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.camera import sources

    if args.detector == "blob":
        try:
            colour = tuple(int(value) for value in args.blob_colour.split(","))
        except ValueError:
            raise UsageError(f"--blob-colour {args.blob_colour!r} must be R,G,B.") from None
        if len(colour) != 3:
            raise UsageError(f"--blob-colour {args.blob_colour!r} must be R,G,B.")
        return sources.ColourBlobDetector(
            colour,
            args.blob_tolerance,
            args.blob_min_area,
            class_id,
        )
    if args.detector == "onnx":
        # lazy: a subcommand imports the library when it runs, so its --help starts fast
        from cblrs.detectors import onnx_camera_detector

        if args.model is None:
            raise UsageError("--detector onnx needs --model MODEL.onnx (a local file).")
        if not 0.0 <= args.confidence <= 1.0 or not 0.0 < args.iou <= 1.0:
            raise UsageError("--confidence must be within 0..1 and --iou within (0, 1].")
        # The tile plan comes from the camera's reference image.
        return onnx_camera_detector(
            args.model, load_reference(args, None), tiling=args.tiling,
            confidence=args.confidence, iou=args.iou, layout=args.layout,
        )
    if args.weights is None:
        raise UsageError("--detector yolo needs --weights MODEL.pt (a local file).")
    try:
        return sources.YoloDetector(args.weights, args.confidence, args.device)
    except ImportError as error:
        raise UsageError(str(error)) from None


def first_sequence(args: argparse.Namespace) -> int:
    """The first message's sequence number: ``--first-sequence``, else the time in
    milliseconds when live (a restarted camera never reuses a number), else 0."""
    if args.first_sequence is not None:
        if args.first_sequence < 0:
            raise UsageError("--first-sequence must be >= 0.")
        return args.first_sequence
    return int(time.time() * 1000) if args.live else 0


def check_delivery_options(args: argparse.Namespace) -> None:
    """UsageError unless the spool and delivery options are in range."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.cli.common import check_non_negative, check_positive

    check_positive(args.spool_max_mb, "--spool-max-mb")
    check_non_negative(args.flush_timeout, "--flush-timeout")
    check_non_negative(args.confirm_timeout, "--confirm-timeout")
    check_positive(args.resend_after, "--resend-after")


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs camera`` with its parsed arguments; the exit code.

    SIGINT/SIGTERM (:mod:`cblrs.cli.stopping`): while it starts, it stops at once; once it
    sends, it stops after the current frame, waits a few seconds for the broker and keeps
    the rest in its spool; a second signal stops it at once."""
    held: dict[str, Any] = {}
    try:
        return _run(args, args.signals, held)
    except Interrupted as interrupted:
        where = ("while starting" if "spool" not in held
                 else "at once" if "sending" in held else "while connecting")
        kept = held.get("unconfirmed", 0)
        print(f"cblrs camera: stopped by {interrupted.name} {where}; "
              + (f"{kept} messages kept in {held['spool']}, sent at the next start."
                 if kept else "nothing left to send."), file=sys.stderr)
        return EXIT_UNCONFIRMED if kept else 0


def _run(args: argparse.Namespace, signals: Any, held: dict[str, Any]) -> int:
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.camera.camera_node import CameraNode, camera_last_will
    from cblrs.runtime.camera.spool import Spool, run_identity
    from cblrs.runtime.transport.mqtt_transport import MqttTransport
    from cblrs.runtime.transport.protocol import Will
    from cblrs.runtime.transport.topics import validate_camera_id

    validate_camera_id(args.camera)
    if not (args.speed > 0 and args.speed < float("inf")):
        raise UsageError("--speed must be a finite number greater than 0.")
    check_delivery_options(args)
    nats = uses_nats(args)
    settings = None if nats else mqtt_settings(args)
    frames, expected_size = build_source(args)
    reference = load_reference(args, expected_size)
    plane_ids = reference.planes.ids
    plane_id = args.plane
    if plane_id is None:
        if len(plane_ids) != 1:
            raise UsageError(f"the reference has planes {plane_ids}; choose one with --plane.")
        plane_id = plane_ids[0]
    elif plane_id not in plane_ids:
        raise UsageError(f"--plane {plane_id} is not in the reference (planes {plane_ids}).")
    folder = Path(os.environ.get(SPOOL_ENVIRONMENT) or DEFAULT_SPOOL_FOLDER).expanduser()
    spool_path = args.spool if args.spool is not None else folder / f"{plane_id}-{args.camera}.db"
    spool = Spool(spool_path, max_bytes=int(args.spool_max_mb * 2**20),
                  run=run_identity(vars(args), plane_id))
    held["spool"] = spool_path
    if len(spool):
        logger.info("camera %s: %d unconfirmed messages from an earlier run are sent first",
                    args.camera, len(spool))
    topic, payload = camera_last_will(plane_id, args.camera)
    client_id = args.client_id or f"cblrs-camera-{plane_id}-{args.camera}"
    if nats:
        transport = camera_transport(args, client_id)
    else:
        # A persistent session: the matcher's confirmations wait at the broker while the
        # camera is away, so a restarted camera does not send again what was stored.
        transport = MqttTransport(client_id, settings, persistent=True, will=Will(topic, payload))
    node = CameraNode(
        transport,
        plane_id,
        args.camera,
        reference,
        realtime=args.realtime,
        speed=args.speed,
        epoch=args.epoch,
        first_sequence=first_sequence(args),
        drop_hidden_feet=(
            args.hidden_feet == "drop" or (args.hidden_feet == "auto" and args.dataset is None)
        ),
        flush_timeout_s=args.flush_timeout,
        confirm_timeout_s=args.confirm_timeout,
        spool=spool,
        resend_after_s=args.resend_after,
        clear_retained=True,
    )
    started = time.perf_counter()
    try:
        # A signal while connecting (a broker that does not answer) ends it at once.
        if nats:
            # A login the servers refuse later (they were away at first) stops the node.
            transport.on_failure = node.fail
            connect_or_spool(transport, f"in the spool {spool_path}")
        else:
            connect_or_queue(transport, f"in the spool {spool_path}")
        signals.arm(node.stop)
        held["sending"] = True
        report = node.run(frames, connect=False)
    except BaseException:
        held["unconfirmed"] = len(spool)
        transport.close(unclean=True, timeout=1.0)
        spool.close()
        raise
    # Stopped by a signal: what the broker has not taken stays in the spool anyway.
    transport.close(timeout=1.0 if signals.received else 2.0)
    spool.close()
    signals.finished()
    summary = report.to_dict()
    summary["wall_s"] = time.perf_counter() - started
    summary["spool"] = str(spool_path)
    summary["stopped_by"] = signals.received
    if args.json:
        print_json(summary)
    else:
        print(_summary_line(report, spool_path, args.confirm_timeout))
    skipped = sum(report.frames_skipped.values())
    if skipped and skipped == report.frames:
        raise InputError(
            f"every one of the {skipped} frames had an unusable image ("
            + ", ".join(f"{count} {reason}" for reason, count in
                        sorted(report.frames_skipped.items()))
            + "): nothing was sent."
        )
    if report.refusal is not None:
        print(f"cblrs camera: error: {report.refusal}.", file=sys.stderr)
        return 1
    done = report.confirmed_all if args.confirm_timeout > 0 else report.flushed
    return 0 if done else EXIT_UNCONFIRMED


def _summary_line(report: Any, spool_path: Path, confirm_timeout: float) -> str:
    head = (
        f"camera {report.camera_id} (plane {report.plane_id}): {report.messages} messages, "
        f"{report.detections} detections ({report.located} located), "
        f"{report.bytes / 1024:.1f} kB in {report.elapsed_s:.2f} s; "
    )
    details = []
    if report.frames_skipped:
        details.append("frames skipped, unusable image: " + ", ".join(
            f"{count} {reason}" for reason, count in sorted(report.frames_skipped.items())))
    if report.boxes_rejected:
        details.append("boxes dropped: " + ", ".join(
            f"{count} {reason}" for reason, count in sorted(report.boxes_rejected.items())))
    if report.rejected_by_matcher:
        details.append("rejected by the matcher: " + ", ".join(
            f"{count} {reason}" for reason, count in sorted(report.rejected_by_matcher.items())))
    if report.dropped_from_spool:
        details.append(f"{report.dropped_from_spool} dropped by the full spool")
    tail = f" ({'; '.join(details)})" if details else ""
    if report.refusal is not None:
        return head + f"REFUSED by the broker; {report.unconfirmed} kept in {spool_path}" + tail
    if report.confirmed_all:
        return head + "all confirmed stored by the matcher" + tail
    if report.flushed and confirm_timeout <= 0:
        return (head + f"all acknowledged by the broker (not waiting for the matcher; "
                f"{report.unconfirmed} kept in {spool_path} until it confirms)" + tail)
    if report.flushed:
        return (head + f"acknowledged by the broker, but {report.unconfirmed} not yet confirmed "
                f"by a matcher: kept in {spool_path}, sent again on the next start" + tail)
    return (head + f"NOT all acknowledged by the broker: {report.unconfirmed} kept in "
            f"{spool_path}, sent on the next start" + tail)
