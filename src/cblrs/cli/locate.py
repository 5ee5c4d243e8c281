"""``cblrs locate``: reference PNG + pixels or boxes -> world positions on the plane."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

from cblrs.calibration import WILDTRACK_CAMERAS
from cblrs.cli.common import InputError, UsageError, add_output_options, format_table, print_json
from cblrs.edge import GROUND_DEPTH_OFFSET_M, box_rejections, location_status
from cblrs.errors import DatasetError
from cblrs.locate import ColorLocator
from cblrs.reference import ReferenceImage
from cblrs.targeting import target_pixels

WITHIN_M = 0.5  # the "within 0.5 m of ground truth"


def register(subparsers) -> None:
    """Add the ``cblrs locate`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "locate",
        help="world positions of pixels or boxes from a reference image",
        description=(
            "Look up world positions (metres) in a colour reference PNG, for pixels, for the "
            "target points of boxes, or for the annotated boxes of a WILDTRACK frame "
            "(then also compared with the ground truth)."
        ),
    )
    parser.add_argument("reference", type=Path, metavar="REFERENCE.png")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--pixels", metavar='"x,y;x,y"', help="pixel coordinates")
    source.add_argument(
        "--boxes",
        type=Path,
        metavar="FILE",
        help="rows 'x_min y_min x_max y_max [class]' (spaces or commas, # comments)",
    )
    source.add_argument(
        "--dataset", type=Path, metavar="WILDTRACK_DIR", help="use a WILDTRACK frame's boxes"
    )
    parser.add_argument("--frame", type=int, help="WILDTRACK frame number (with --dataset)")
    parser.add_argument(
        "--vtp", type=float, default=1.0, help="vertical targeting position, 0=top 1=bottom"
    )
    parser.add_argument(
        "--hpos", type=float, default=0.5, help="horizontal targeting position, 0=left 1=right"
    )
    add_output_options(parser)
    parser.set_defaults(handler=run)


def parse_pixels(text: str) -> np.ndarray:
    """``"x,y;x,y"`` -> (N, 2) float pixels."""
    points = []
    for item in (part.strip() for part in text.split(";")):
        if not item:
            continue
        values = [value for value in re.split(r"[,\s]+", item) if value]
        try:
            point = [float(value) for value in values]
        except ValueError:
            raise UsageError(f"pixel {item!r} is not a pair of numbers x,y.") from None
        if len(point) != 2 or not np.all(np.isfinite(point)):
            raise UsageError(f"pixel {item!r} must be two finite numbers x,y.")
        points.append(point)
    if not points:
        raise UsageError('--pixels holds no pixel; write them as "x,y;x,y".')
    return np.array(points, dtype=np.float64)


def read_boxes_file(path: Path) -> tuple[np.ndarray, list[str]]:
    """Boxes (N, 4) pixels and class names ("" when not given) from a text file."""
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise InputError(f"boxes file {path} does not exist.") from None
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read boxes file {path}: {error}.") from None
    boxes, classes = [], []
    for number, line in enumerate(lines, start=1):
        content = line.split("#", 1)[0].strip()
        if not content:
            continue
        fields = [field for field in re.split(r"[,\s]+", content) if field]
        if len(fields) not in (4, 5):
            raise UsageError(
                f"{path}:{number}: expected 'x_min y_min x_max y_max [class]', "
                f"got {len(fields)} fields."
            )
        try:
            box = [float(field) for field in fields[:4]]
        except ValueError:
            raise UsageError(f"{path}:{number}: box coordinates must be numbers.") from None
        boxes.append(box)
        classes.append(fields[4] if len(fields) == 5 else "")
    return np.array(boxes, dtype=np.float64).reshape(-1, 4), classes


def wildtrack_position(position_id: NDArrayLike) -> np.ndarray:
    """WILDTRACK positionID -> (N, 2) ground position in metres (480 x 1440 grid, 2.5 cm)."""
    position_id = np.asarray(position_id, dtype=np.int64)
    x_cm = -300.0 + 2.5 * (position_id % 480)
    y_cm = -900.0 + 2.5 * (position_id // 480)
    return np.column_stack([x_cm, y_cm]) / 100.0


NDArrayLike = np.ndarray | list


def read_wildtrack_frame_boxes(
    root: Path, frame: int, camera_name: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One camera's annotated boxes in a WILDTRACK frame.

    Returns:
        ``(xyxy, person_ids, ground_truth_xy)``: (N, 4) pixels, (N,) int, (N, 2) metres.
    """
    if camera_name not in WILDTRACK_CAMERAS:
        raise DatasetError(
            f"reference camera {camera_name!r} is not a WILDTRACK camera "
            f"({', '.join(WILDTRACK_CAMERAS)}); render it from the WILDTRACK folder."
        )
    view = WILDTRACK_CAMERAS.index(camera_name)
    path = root / "annotations_positions" / f"{frame:08d}.json"
    if not (root / "annotations_positions").is_dir():
        raise DatasetError(f"{root} has no annotations_positions/ folder.")
    try:
        people = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetError(
            f"WILDTRACK frame {frame} is not annotated ({path} is missing)."
        ) from None
    except (OSError, UnicodeDecodeError, ValueError) as error:
        raise DatasetError(f"{path} is not valid JSON: {error}.") from None
    boxes, person_ids, position_ids = [], [], []
    try:
        for person in people:
            for entry in person["views"]:
                if int(entry["viewNum"]) != view:
                    continue
                box = [float(entry[key]) for key in ("xmin", "ymin", "xmax", "ymax")]
                if box == [-1.0, -1.0, -1.0, -1.0]:
                    continue
                boxes.append(box)
                person_ids.append(int(person["personID"]))
                position_ids.append(int(person["positionID"]))
    except (KeyError, TypeError, ValueError) as error:
        raise DatasetError(f"{path}: unexpected annotation layout ({error}).") from None
    return (
        np.array(boxes, dtype=np.float64).reshape(-1, 4),
        np.array(person_ids, dtype=np.int64),
        wildtrack_position(position_ids).reshape(-1, 2),
    )


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs locate`` with its parsed arguments; the exit code."""
    for name in ("vtp", "hpos"):
        value = getattr(args, name)
        if not 0.0 <= value <= 1.0:
            raise UsageError(f"--{name} must be within 0..1, got {value}.")
    if args.frame is not None and args.dataset is None:
        raise UsageError("--frame needs --dataset WILDTRACK_DIR.")
    if args.dataset is not None and args.frame is None:
        raise UsageError("--dataset needs --frame N.")
    reference = ReferenceImage.load(args.reference)
    locator = ColorLocator(reference)
    classes: list[str] = []
    boxes = person_ids = truth_xy = None
    inside = None
    if args.pixels is not None:
        pixels = parse_pixels(args.pixels)
    else:
        if args.boxes is not None:
            boxes, classes = read_boxes_file(args.boxes)
        else:
            boxes, person_ids, truth_xy = read_wildtrack_frame_boxes(
                args.dataset, args.frame, reference.camera_name
            )
        pixels, inside = target_pixels(boxes, args.hpos, args.vtp, reference.image_size)
    world_xy, valid = locator.locate(pixels)
    rejections: list[str | None] = [None] * len(pixels)
    sends: list[str] = []
    if boxes is not None and inside is not None:
        # The camera's rule (cblrs.edge): refused boxes never get a position, and the
        # "camera sends" column says what a camera would send for each box.
        rejections = box_rejections(boxes, reference.image_size)
        vehicles = np.array([name in GROUND_DEPTH_OFFSET_M for name in classes]
                            if classes else [False] * len(boxes), dtype=bool)
        sends = location_status(boxes, pixels, inside, valid, np.full(len(boxes), args.vtp),
                                vehicles, reference.image_size)
        valid = valid & np.array([reason is None for reason in rejections], dtype=bool)
    rows = []
    for index in range(len(pixels)):
        row: dict = {"index": index}
        if boxes is not None and inside is not None:
            row["box"] = [value if np.isfinite(value) else None for value in boxes[index].tolist()]
            row["target_inside"] = bool(inside[index]) and rejections[index] is None
            row["rejected"] = rejections[index]
            row["camera_sends"] = (f"nothing ({rejections[index]})" if rejections[index]
                                   else "location" if sends[index] == "located"
                                   else f"no location ({sends[index]})")
        if classes:
            row["class"] = classes[index]
        row["pixel"] = pixels[index].tolist() if rejections[index] is None else None
        row["x"] = float(world_xy[index, 0]) if valid[index] else None
        row["y"] = float(world_xy[index, 1]) if valid[index] else None
        row["valid"] = bool(valid[index])
        if truth_xy is not None and person_ids is not None:
            row["person_id"] = int(person_ids[index])
            row["truth"] = truth_xy[index].tolist()
            error = float(np.hypot(*(world_xy[index] - truth_xy[index])))
            row["error_m"] = error if valid[index] else None
        rows.append(row)
    summary = _summary(rows) if truth_xy is not None else None
    if args.json:
        output: dict = {
            "reference": str(args.reference),
            "camera": reference.camera_name,
            "positions": rows,
        }
        if summary is not None:
            output["frame"] = args.frame
            output["summary"] = summary
        print_json(output)
        return 0
    headers = ["#", "pixel x", "pixel y", "x m", "y m", "valid"]
    table = []
    for row in rows:
        cells = [
            row["index"],
            "-" if row["pixel"] is None else f"{row['pixel'][0]:.1f}",
            "-" if row["pixel"] is None else f"{row['pixel'][1]:.1f}",
            _metres(row["x"]),
            _metres(row["y"]),
            "yes" if row["valid"] else "no",
        ]
        if "target_inside" in row:
            # A target clamped to the image border (the box is cut off) is only a bound.
            cells.append(f"rejected: {row['rejected']}" if row["rejected"]
                         else "yes" if row["target_inside"] else "clamped")
            cells.append(row["camera_sends"])
        if classes:
            cells.insert(1, row["class"] or "-")
        if summary is not None:
            cells += [
                row["person_id"],
                f"{row['truth'][0]:.3f}",
                f"{row['truth'][1]:.3f}",
                _metres(row["error_m"]),
            ]
        table.append(cells)
    if boxes is not None:
        headers += ["in image", "camera sends"]
    if classes:
        headers.insert(1, "class")
    if summary is not None:
        headers += ["person", "true x m", "true y m", "error m"]
    print(format_table(headers, table))
    if summary is not None:
        print(
            f"camera {reference.camera_name}, frame {args.frame}: "
            f"{summary['located']}/{summary['people']} people located, median error "
            f"{_metres(summary['median_error_m'])} m, "
            f"{100 * summary['share_within_0_5_m']:.0f}% within {WITHIN_M} m"
        )
    return 0


def _summary(rows: list[dict]) -> dict:
    errors = np.array([row["error_m"] for row in rows if row["error_m"] is not None])
    return {
        "people": len(rows),
        "located": len(errors),
        "median_error_m": float(np.median(errors)) if len(errors) else None,
        # Unlocated people count as misses.
        "share_within_0_5_m": float(np.sum(errors <= WITHIN_M) / len(rows)) if rows else 0.0,
    }


def _metres(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"
