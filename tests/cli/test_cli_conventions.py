"""Conventions every subcommand keeps: one spelling of the data set's location (old ones still
accepted, hidden), an example in every --help, exit code 2 for usage errors and 1 for runtime
failures, one sentence and no traceback."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

from cblrs.cli.common import resolve_dataset
from cblrs.cli.main import build_parser, main

WILDTRACK = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "wildtrack"


def _subcommands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield (*path, name), child
                yield from _subcommands(child, (*path, name))


SUBCOMMANDS = [path for path, _ in _subcommands(build_parser())]


def test_every_subcommand_is_walked():
    assert ("track",) in SUBCOMMANDS and ("bench", "mqtt") in SUBCOMMANDS
    assert len(SUBCOMMANDS) >= 30


@pytest.mark.parametrize("path", SUBCOMMANDS, ids=" ".join)
def test_every_help_shows_an_example_and_exits_0(path, capsys):
    with pytest.raises(SystemExit) as stopped:
        main([*path, "--help"])
    assert stopped.value.code == 0
    text = capsys.readouterr().out
    assert "example" in text and f"cblrs {' '.join(path)}" in text.split("example")[-1]
    assert "DATASET_DIR" not in text and "--wildtrack" not in text and "--calibration" not in text


def _run(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cblrs.cli.main", *argv],
                          capture_output=True, text=True, timeout=300)


@pytest.mark.skipif(not WILDTRACK.is_dir(), reason="WILDTRACK not in ../shared")
def test_the_old_positional_gives_the_same_tracks_as_dataset(tmp_path):
    new = _run("track", "--dataset", str(WILDTRACK), "--frames", "0:40",
               "--out", str(tmp_path / "new.txt"), "--quiet")
    old = _run("track", str(WILDTRACK), "--frames", "0:40", "--out", str(tmp_path / "old.txt"),
               "--quiet")
    assert new.returncode == old.returncode == 0, new.stderr + old.stderr
    assert (tmp_path / "new.txt").read_bytes() == (tmp_path / "old.txt").read_bytes()
    assert len((tmp_path / "new.txt").read_bytes()) > 1000


@pytest.mark.parametrize(
    ("argv", "old"),
    [(["bench", "lookup", "--calibration", "somewhere"], "--calibration"),
     (["experiment", "counts", "--wildtrack", "somewhere"], "--wildtrack"),
     (["eval", "somewhere", "tracks.txt"], None),
     (["site", "init", "somewhere", "--out", "s.yaml"], None)],
)
def test_old_spellings_land_in_dataset(argv, old, capsys):
    args = build_parser().parse_args(argv)
    resolve_dataset(args)
    assert args.dataset == Path("somewhere")
    note = capsys.readouterr().err
    assert (f"{old} is now spelled --dataset" in note) if old else note == ""


@pytest.mark.parametrize(
    ("argv", "message"),
    [(["track", "a", "--dataset", "b", "--out", "t.txt"], "name different folders"),
     (["track", "--out", "t.txt"], "required: --dataset"),
     (["experiment", "resolution", "--wildtrack", "a", "--dataset", "b"], "different folders"),
     (["track", "--dataset", "x", "--out", "t.txt", "--matcher", "nobody"], "invalid choice"),
     (["track", "--dataset", "x", "--out", "t.txt", "--frames", "9:3"], "frame range"),
     (["track", "--dataset", "x", "--out", "t.txt", "--high-confidence", "2"],
      "--high-confidence is a score"),
     (["track", "--dataset", "x", "--out", "t.txt", "--matcher", "paper",
       "--high-confidence", "0.5"], "for --matcher fusion"),
     (["eval", "--dataset", "x"], "required"),
     (["bench", "lookup", "--n", "0"], "--n"),
     (["nonsense"], "invalid choice")],
)
def test_usage_errors_exit_2_with_one_sentence(argv, message):
    result = _run(*argv)
    assert result.returncode == 2, result.stderr
    assert message in result.stderr and "Traceback" not in result.stderr


@pytest.mark.parametrize(
    "argv",
    [["track", "--dataset", "/nonexistent/folder", "--out", "t.txt"],
     ["eval", "--dataset", "/nonexistent/folder", "/nonexistent/tracks.txt"],
     ["show", "/nonexistent/reference.png", "--out", "x.png"]],
)
def test_runtime_failures_exit_1_with_one_sentence(argv, tmp_path):
    result = subprocess.run([sys.executable, "-m", "cblrs.cli.main", *argv], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 1, result.stderr
    lines = [line for line in result.stderr.splitlines() if "error" in line]
    assert len(lines) == 1 and "Traceback" not in result.stderr


def test_the_listed_summaries_are_the_registered_ones():
    """`cblrs --help` lists each subcommand without importing it: its line must match."""
    from cblrs.cli.main import SUBCOMMANDS

    registered = {}
    for action in build_parser()._actions:
        if isinstance(action, argparse._SubParsersAction):
            registered = {choice.dest: choice.help for choice in action._choices_actions}
    assert registered == {name.replace("_", "-"): text for name, text in SUBCOMMANDS.items()}


def test_help_does_not_import_the_library():
    code = ("import sys; from cblrs.cli.main import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in ('scipy', 'cv2', 'onnxruntime', 'cblrs.matching', "
            "'cblrs.runtime', 'matplotlib') if m in sys.modules]\n"
            "print('HEAVY:' + ','.join(heavy))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "HEAVY:"



def test_loading_a_site_does_not_import_scipy():
    """``cblrs up``, ``dashboard`` and every service given ``--site`` import the site package;
    SciPy (~0.5-1 s of CPU per process) is imported only by a calibration fit."""
    code = ("import sys, cblrs.site, cblrs.up, cblrs.dashboard.app\n"
            "print('SCIPY:' + ','.join(m for m in sys.modules if m.split('.')[0] == 'scipy'))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "SCIPY:"

def _leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    children = [action for action in parser._actions
                if isinstance(action, argparse._SubParsersAction)]
    if not children:
        yield path, parser
    for action in children:
        for name, child in action.choices.items():
            yield from _leaves(child, (*path, name))


LEAVES = list(_leaves(build_parser()))


@pytest.mark.parametrize(("path", "parser"), LEAVES, ids=[" ".join(p) for p, _ in LEAVES])
def test_every_subcommand_takes_json_and_quiet(path, parser):
    # Issue 21: `site init` refused --quiet (as did site check/export, calibrate, dashboard and
    # bench mqtt) although docs/cli.md says every subcommand takes it.
    options = {option for action in parser._actions for option in action.option_strings}
    assert {"--json", "--quiet"} <= options, " ".join(path)


MULTIVIEWX = WILDTRACK.parent / "multiviewx"


@pytest.mark.skipif(not MULTIVIEWX.is_dir(), reason="MultiviewX not in ../shared")
def test_render_takes_the_data_set_as_dataset(tmp_path, capsys):
    # Issue 21: `cblrs render` was the one subcommand without --dataset.
    assert main(["render", "--dataset", str(MULTIVIEWX), "--out", str(tmp_path / "new"),
                 "--bits", "8", "--quiet"]) == 0
    assert main(["render", str(MULTIVIEWX), "--out", str(tmp_path / "old"), "--bits", "8",
                 "--quiet"]) == 0
    new = sorted((tmp_path / "new").iterdir())
    assert [path.name for path in new] == [f"Camera{index}.png" for index in range(1, 7)]
    for path in new:
        assert path.read_bytes() == (tmp_path / "old" / path.name).read_bytes()
    capsys.readouterr()
    assert main(["render", str(WILDTRACK), "--dataset", str(MULTIVIEWX), "--out",
                 str(tmp_path / "x")]) == 2
    assert "CALIBRATION and --dataset name different folders" in capsys.readouterr().err
    assert main(["render", "--dataset", str(tmp_path / "nowhere"), "--out",
                 str(tmp_path / "x")]) == 1


def test_bench_mqtt_writes_its_results_to_out(tmp_path, capsys):
    # Issue 21: `cblrs bench mqtt` refused --out, which every other benchmark takes.
    assert main(["bench", "mqtt", "--stages", "--cameras", "1", "--out", str(tmp_path),
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    written = (tmp_path / "bench_mqtt_stages.md").read_text()
    assert written.strip() == printed.strip() and "1 cameras: decode" in written
    document = json.loads((tmp_path / "bench_mqtt_stages.json").read_text())
    assert document["stages"][0]["cameras"] == 1
    (tmp_path / "file").write_text("")
    assert main(["bench", "mqtt", "--out", str(tmp_path / "file")]) == 2
