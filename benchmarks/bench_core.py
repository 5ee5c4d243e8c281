"""Core benchmark (issue 2): render time per 1080p reference (8 and 16 bit, with and without
lens distortion), one-point and batched lookup for the homography, LUT and colour localisers,
and PNG vs LUT vs JSON sizes. Same measurements as ``cblrs bench lookup`` + ``cblrs bench render``.

    python benchmarks/bench_core.py [--n 100000] [--repeats 5] [--json] [--calibration DIR]
"""

from __future__ import annotations

import argparse
import json
import sys

from cblrs.bench.lookup import benchmark_lookup
from cblrs.bench.render import benchmark_render
from cblrs.bench.report import lookup_report, render_report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100_000, help="random pixels")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per measurement")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--calibration", default=None, help="WILDTRACK folder")
    parser.add_argument("--json", action="store_true", help="print one JSON document")
    args = parser.parse_args(argv)
    if args.n <= 0 or args.repeats <= 0:
        parser.error("--n and --repeats must be positive")
    lookups = {
        bits: benchmark_lookup(args.n, args.repeats, args.seed, bits, args.calibration)
        for bits in (8, 16)
    }
    render = benchmark_render(args.repeats, args.calibration)
    if args.json:
        print(json.dumps({"lookup_8bit": lookups[8], "lookup_16bit": lookups[16],
                          "render": render}, indent=2))
    else:
        print(render_report(render))
        for result in lookups.values():
            print()
            print(lookup_report(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
