"""`cblrs bench track`: cblrs track and the homography + norfair baselines, whole process."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from cblrs.bench.track import (
    BASELINES,
    CBLRS,
    BenchmarkError,
    bytecode_environment,
    run_process,
    track_report,
)
from cblrs.cli.main import main

BASELINE_SCRIPT = str(Path(__file__).resolve().parents[2] / "src" / "cblrs" / "bench"
                      / "norfair_baseline.py")


def test_track_beside_norfair_on_wildtrack(wildtrack_root, tmp_path, capsys):
    argv = ["bench", "track", "--dataset", str(wildtrack_root), "--repeats", "1", "--warmup", "0",
            "--out", str(tmp_path), "--json", "--quiet"]
    assert main(argv) == 0
    result = json.loads(capsys.readouterr().out)
    names = {CBLRS, *BASELINES}
    assert set(result["runs"]) == set(result["medians"]) == set(result["scores"]) == names
    for name in names:
        (run,) = result["runs"][name]
        assert run["wall_s"] > 0 and 0 < run["cpu_s"] and 30 < run["peak_mib"] < 4000
        assert result["medians"][name] == run
    for baseline in BASELINES:
        expected = result["runs"][CBLRS][0]["wall_s"] / result["runs"][baseline][0]["wall_s"]
        assert result["ratios"][baseline]["wall_s"]["median"] == pytest.approx(expected)
    scores = result["scores"]
    # Real trackers on real boxes: cblrs on its home data, both baselines far below it, and
    # the baseline that never merges the cameras' views with far too many identities.
    assert scores[CBLRS]["HOTA"] > 90 and scores[CBLRS]["ids"] < 260
    assert 40 < scores["norfair merged"]["HOTA"] < scores[CBLRS]["HOTA"]
    assert scores["norfair every-box"]["ids"] > 2 * scores["norfair merged"]["ids"]
    assert result["load_average"]["start"] >= 0
    stages = result["stages_cpu_s"]
    assert next(iter(stages)) == "numpy import" and "fusion tracker" in stages
    assert all(seconds >= 0 for seconds in stages.values())
    # The stages add up to about one cblrs track process (its CLI and the interpreter aside).
    assert 0.4 < sum(stages.values()) / result["runs"][CBLRS][0]["cpu_s"] < 1.3
    assert "the tracker's views (reference colours)" in stages
    markdown = (tmp_path / "bench_track.md").read_text()
    assert "| cblrs track |" in markdown and "| norfair every-box |" in markdown
    # The figures as printed: each command's wall, CPU and peak memory, and the ratios.
    assert re.search(r"\| cblrs track \| [\d.]+ \| [\d.]+ \| \d+ \|", markdown)
    assert re.search(r"\| norfair merged \| [\d.]+ \([\d.]+-[\d.]+\) \| [\d.]+ \(", markdown)
    assert track_report(result) in markdown


def test_baseline_script_refuses_bad_arguments(tmp_path):
    usage = subprocess.run([sys.executable, BASELINE_SCRIPT], capture_output=True, text=True)
    assert usage.returncode == 2 and "usage: norfair_baseline.py" in usage.stderr
    missing = subprocess.run([sys.executable, BASELINE_SCRIPT, str(tmp_path), "o.txt"],
                             capture_output=True, text=True)
    assert missing.returncode == 1
    assert "is not a WILDTRACK folder" in missing.stderr and "Traceback" not in missing.stderr


def test_a_failing_process_is_one_sentence():
    with pytest.raises(BenchmarkError, match=r"exited with 3: the last words"):
        run_process([sys.executable, "-c",
                     "import sys; print('the last words', file=sys.stderr); sys.exit(3)"])


def test_track_benchmark_needs_positive_repeats(wildtrack_root, capsys):
    argv = ["bench", "track", "--dataset", str(wildtrack_root), "--repeats", "0"]
    assert main(argv) == 2
    assert "--repeats must be a positive integer" in capsys.readouterr().err


def test_processes_get_a_bytecode_cache(tmp_path, monkeypatch):
    """An environment that forbids bytecode (PYTHONDONTWRITEBYTECODE) would time the compiler
    at every start: the benchmark's processes cache it in a folder of their own."""
    monkeypatch.setenv("PYTHONDONTWRITEBYTECODE", "1")
    environment = bytecode_environment(tmp_path / "pycache")
    assert "PYTHONDONTWRITEBYTECODE" not in environment
    module = tmp_path / "cached_module.py"
    module.write_text("VALUE = 1\n")
    run_process([sys.executable, "-c", "import cached_module"],
                dict(environment, PYTHONPATH=str(tmp_path)))
    assert list((tmp_path / "pycache").rglob("cached_module*.pyc"))
    assert not (tmp_path / "__pycache__").exists()  # nothing written beside the sources


def test_a_big_parent_does_not_inflate_the_peak_of_a_small_command():
    """A forked child's resident set starts as its parent's and Linux keeps that high-water
    mark through exec: from a 1 GiB test worker, a 90 MiB ``cblrs track`` once measured
    1,000+ MiB. The command is started from a small interpreter instead."""
    import numpy as np

    from cblrs.bench.track import run_process

    ballast = np.ones(600 * 2**20 // 8)  # 600 MiB in this process, touched
    measured = run_process([sys.executable, "-c", "pass"])
    assert ballast.sum() > 0
    assert 0 < measured["peak_mib"] < 100, measured
    assert measured["wall_s"] > 0 and measured["cpu_s"] > 0
