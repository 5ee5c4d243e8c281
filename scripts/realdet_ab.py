"""A/B of fusion options over ``cblrs experiment tracking``'s rows, scenes built once.

    python scripts/realdet_ab.py --option confirm_support_share=0 --scenes wildtrack,crowd

Each selected row of :func:`cblrs.experiments.tracking.default_cases` (held-out first) is
tracked twice on the same scene and references: with ``--option`` (A, e.g. a stage turned
off: the tracker as before it) and with the defaults (B), and both scores are printed as
they come (HOTA, AssA, DetA, ids).
"""

from __future__ import annotations

import argparse
import json
import sys

from cblrs.experiments.tracking import TrackingSetup, build_scene, default_cases, run_case
from cblrs.pipeline import render_scene_references


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--option", action="append", default=[], help="name=JSON value (A)")
    parser.add_argument("--scenes", default="", help="comma-separated; default all")
    parser.add_argument("--boxes", default="", help="comma-separated kinds; default all")
    parser.add_argument("--no-held-out", action="store_true", help="skip the held-out rows")
    args = parser.parse_args()
    options = tuple((name, json.loads(value)) for name, _, value in
                    (text.partition("=") for text in args.option))
    cases = [case for case in default_cases()
             if (not args.scenes or case.scene in args.scenes.split(","))
             and (not args.boxes or case.boxes in args.boxes.split(","))
             and not (args.no_held_out and case.held_out)]
    cases.sort(key=lambda case: not case.held_out)
    built: dict = {}
    for case in cases:
        key = (case.scene, case.seed, case.size)
        if key not in built:
            scene = build_scene(case, TrackingSetup())
            built[key] = (scene, render_scene_references(scene))
        scene, references = built[key]
        rows = [run_case(case, scene, references, TrackingSetup(matcher_options=options)),
                run_case(case, scene, references, TrackingSetup())]
        before, after = rows
        print(f"{before['scene']}{' (held out)' if case.held_out else ''} | {before['boxes']} | "
              + " | ".join(f"{before[k]:.1f} -> {after[k]:.1f}" for k in ("HOTA", "AssA", "DetA"))
              + f" | {before['predicted_ids']} -> {after['predicted_ids']} / {after['true_ids']}",
              flush=True)
    sys.stdout.flush()


if __name__ == "__main__":
    main()
