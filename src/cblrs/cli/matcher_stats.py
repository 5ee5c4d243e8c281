"""``cblrs matcher --stats DB``: what a matcher database holds, as a table or JSON."""

from __future__ import annotations

from pathlib import Path

from cblrs.cli.common import format_table, print_json


def show_stats(path: Path, as_json: bool) -> int:
    """Print what a matcher database holds (``cblrs matcher --stats``); the exit code."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.matching.fusion import clock_report
    from cblrs.runtime.matcher.store import RuntimeStore
    from cblrs.runtime.outputs.analytics_store import count_summary, line_rules, read_counts

    with RuntimeStore(path, read_only=True) as store:
        summary = store.summary()
        summary["clocks"] = clock_report(
            store.matcher_state(), (summary.get("settings") or {}).get("camera_ids") or []
        )
        try:
            summary["analytics"] = count_summary(read_counts(store))
            summary["analytics"]["line_rules"] = line_rules(store)
        except Exception:  # a file written before the analytics tables: none to show
            summary["analytics"] = {"lines": {}, "zones": {}}
    if as_json:
        print_json(summary)
        return 0
    settings = summary.get("settings") or {}
    print(
        f"{path}: plane {settings.get('plane_id')}, cameras "
        f"{', '.join(settings.get('camera_ids') or [])}, matcher {settings.get('matcher')}"
    )
    rows = [[name, value] for name, value in summary["counters"].items()]
    rows += [[f"inbox {status}", count] for status, count in sorted(summary["inbox"].items())]
    rows += [["track rows", summary["track_rows"]], ["track ids", summary["track_ids"]]]
    rows += [[f"clock offset {name} (s)", f"{report['offset_s']:+.3f}"
              + (" beyond tolerance" if report["beyond_tolerance"] else "")]
             for name, report in (summary["clocks"] or {}).items()]
    rules = summary["analytics"].get("line_rules") or {}
    for line, row in sorted(summary["analytics"]["lines"].items()):
        rule = f" (counted when: {rules[line]})" if line in rules else ""
        rows.append([f"line {line} +/-", f"{row.get('positive', 0):.0f} / "
                     f"{row.get('negative', 0):.0f}{rule}"])
    for zone, row in sorted(summary["analytics"]["zones"].items()):
        rows.append([f"zone {zone} entries/exits/visits",
                     f"{row.get('entries', 0):.0f} / {row.get('exits', 0):.0f} / "
                     f"{row.get('visits', 0):.0f} (mean dwell {row['mean_dwell_s']:.1f} s)"])
    print(format_table(["counter", "value"], rows))
    return 0
