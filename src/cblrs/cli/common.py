"""Helpers shared by the subcommands: errors, JSON output, progress bars."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from cblrs.errors import CblrsError

T = TypeVar("T")


class UsageError(Exception):
    """A mistake in the command line; printed as one sentence, exit code 2."""


class InputError(CblrsError):
    """A file or folder the command line names is missing or unreadable; printed as one
    sentence, exit code 1 (a runtime failure, like every :class:`~cblrs.errors.CblrsError`)."""


def parse_frame_range(text: str) -> tuple[int | None, int | None]:
    """``"FIRST:LAST"`` (inclusive native frame numbers, either side may be empty) -> (first, last).

    ``"100:"`` is frame 100 onwards, ``":995"`` up to 995, ``":"`` everything (None, None).

    Raises:
        UsageError: no colon, a side that is not a non-negative integer, or first > last.
    """
    if text.count(":") != 1:
        raise UsageError(f"frame range {text!r} must be FIRST:LAST, e.g. 0:995, 100: or :995.")
    bounds: list[int | None] = []
    for side in text.split(":"):
        side = side.strip()
        if not side:
            bounds.append(None)
            continue
        if not (side.isascii() and side.isdigit()):
            raise UsageError(
                f"frame range {text!r}: {side!r} is not a non-negative integer frame number."
            )
        bounds.append(int(side))
    first, last = bounds
    if first is not None and last is not None and first > last:
        raise UsageError(f"frame range {text!r} is empty: FIRST {first} is after LAST {last}.")
    return first, last


def check_positive(value: float, option: str) -> float:
    """``value`` if it is a finite number > 0, else a :class:`UsageError` naming ``option``."""
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"{option} must be a finite number greater than 0, got {value}.")
    return value


def check_non_negative(value: float, option: str) -> float:
    """``value`` if it is a finite number >= 0, else a :class:`UsageError` naming ``option``."""
    if not (math.isfinite(value) and value >= 0):
        raise UsageError(f"{option} must be a finite number of at least 0, got {value}.")
    return value


def print_json(data: Any) -> None:
    """Print one JSON document to stdout (numpy scalars and arrays are converted)."""
    print(json.dumps(data, indent=2, default=_to_builtin, allow_nan=False))


def _to_builtin(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "__fspath__"):
        return str(value)
    raise TypeError(f"cannot serialise {type(value).__name__} to JSON")


def progress(
    iterable: Iterable[T], description: str, quiet: bool = False, total: int | None = None
) -> Iterator[T]:
    """A tqdm progress bar on stderr, shown only on a terminal and without --quiet."""

    disable = quiet or not sys.stderr.isatty()
    if disable:
        yield from iterable
        return
    # lazy: tqdm reads its version through importlib.metadata (~20 ms); only a bar needs it
    from tqdm import tqdm

    yield from tqdm(iterable, desc=description, total=total, leave=False)


def add_output_options(parser: Any) -> None:
    """Add ``--json`` and ``--quiet``."""
    parser.add_argument("--json", action="store_true", help="print machine-readable JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def format_table(headers: list[str], rows: list[list[Any]]) -> str:
    """A plain-text table with right-aligned numbers."""
    cells = [[_cell(value) for value in row] for row in rows]
    widths = [len(header) for header in headers]
    for row in cells:
        widths = [max(width, len(cell)) for width, cell in zip(widths, row, strict=True)]
    lines = ["  ".join(header.ljust(width) for header, width in zip(headers, widths, strict=True))]
    lines.append("  ".join("-" * width for width in widths))
    for row in cells:
        lines.append("  ".join(cell.rjust(width) for cell, width in zip(row, widths, strict=True)))
    return "\n".join(lines)


def _cell(value: Any) -> str:
    if isinstance(value, float | np.floating):
        return f"{value:.3f}" if np.isfinite(value) else "-"
    return str(value)


# --------------------------------------------------------------------------- data set location
# One spelling for a data set's folder on every subcommand: ``--dataset PATH``. The spellings of
# earlier releases (a positional DATASET_DIR on track, eval and site init; --calibration on
# bench; --wildtrack on experiment) are accepted, hidden from --help, for one more release.


def add_dataset_argument(
    parser: argparse.ArgumentParser,
    help: str,
    *,
    required: bool = False,
    positional_alias: bool = False,
    option_aliases: tuple[str, ...] = (),
    metavar: str = "PATH",
) -> None:
    """Add ``--dataset PATH`` (dest ``dataset``) and the hidden old spellings of it.

    Call :func:`resolve_dataset` on the parsed arguments (``cblrs.cli.main`` does) to merge
    the old spellings into ``args.dataset`` and check ``required``.
    """
    parser.add_argument("--dataset", type=Path, default=None, metavar=metavar, help=help)
    aliases: list[tuple[str, str]] = []
    if positional_alias:
        parser.add_argument(
            "dataset_positional", nargs="?", type=Path, default=None, help=argparse.SUPPRESS
        )
        aliases.append(("dataset_positional", "the positional DATASET_DIR"))
    for option in option_aliases:
        destination = "dataset_alias_" + option.lstrip("-").replace("-", "_")
        parser.add_argument(option, dest=destination, type=Path, default=None,
                            help=argparse.SUPPRESS)
        aliases.append((destination, option))
    parser.set_defaults(dataset_aliases=tuple(aliases), dataset_required=required)


def resolve_dataset(args: argparse.Namespace) -> None:
    """Merge the old spellings of ``--dataset`` into ``args.dataset`` (a note on stderr for
    each used); :class:`UsageError` when two spellings disagree or a required one is missing."""
    aliases = getattr(args, "dataset_aliases", None)
    if aliases is None:
        return
    chosen = args.dataset
    for destination, spelling in aliases:
        value = getattr(args, destination, None)
        if value is None:
            continue
        if chosen is not None and Path(value) != Path(chosen):
            raise UsageError(
                f"{spelling} ({value}) and --dataset ({chosen}) name different folders; "
                "give --dataset only."
            )
        if spelling.startswith("--"):
            print(f"cblrs: note: {spelling} is now spelled --dataset; {spelling} will be "
                  "removed in a later release.", file=sys.stderr)
        chosen = value
    if chosen is None and getattr(args, "dataset_required", False):
        raise UsageError("the following argument is required: --dataset PATH.")
    args.dataset = chosen
