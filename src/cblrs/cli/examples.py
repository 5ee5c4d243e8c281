"""One example (or a few) per subcommand, shown at the end of its ``--help``.

Paths are those of the documentation: the data sets in ``../shared/data``, references in ``refs/``.
:func:`cblrs.cli.main.build_parser` attaches them and the help formatter (defaults shown).
"""

from __future__ import annotations

import argparse

WT = "../shared/data/wildtrack"
MVX = "../shared/data/multiviewx"

EXAMPLES: dict[str, list[str]] = {
    "": ["cblrs demo", f"cblrs track --dataset {WT} --out tracks.txt --score",
         "cblrs COMMAND --help"],
    "demo": ["cblrs demo", f"cblrs demo --dataset {WT}",
             f"cblrs demo --dataset {MVX} --detector onnx "
             "--model ../shared/models/yolox_nano.onnx"],
    "site": [f"cblrs site init --dataset {WT} --out site.yaml", "cblrs site check site.yaml"],
    "site init": [f"cblrs site init --dataset {WT} --out site.yaml"],
    "site check": ["cblrs site check site.yaml --for render,matcher"],
    "site export": ["cblrs site export site.yaml --out site-bundle.yaml"],
    "calibrate": ["cblrs calibrate gate.csv --image gate.jpg --picture gate_check.png "
                  "--out gate.json"],
    "render": [f"cblrs render --dataset {WT} --out refs --preview",
               "cblrs render --site site.yaml --out refs",
               "cblrs render --site site.yaml --key site.key --out refs   # pseudo colours"],
    "locate": [f"cblrs locate refs/CVLab1.png --dataset {WT} --frame 0",
               'cblrs locate refs/CVLab1.png --pixels "960,1000;10,10" --json'],
    "show": ["cblrs show refs/CVLab1.png --out CVLab1_grid.png --grid 1"],
    "track": [f"cblrs track --dataset {WT} --out tracks.txt --score",
              f"cblrs track --dataset {WT} --key site.key --out pseudo-tracks.txt",
              f"cblrs track --dataset {WT} --out tracks.txt --drop 0.2 --jitter 0.05 --seed 1",
              f"cblrs track --dataset {MVX} --out tracks.txt --detector onnx "
              "--model ../shared/models/yolox_nano.onnx"],
    "eval": [f"cblrs eval --dataset {WT} tracks.txt",
             f"cblrs eval --dataset {WT} pseudo-tracks.txt --key site.key"],
    "pseudo": ["cblrs pseudo keygen --out site.key",
               "cblrs pseudo site site.yaml --key site.key --out pseudo-site.yaml"],
    "pseudo keygen": ["cblrs pseudo keygen --out site.key"],
    "pseudo site": ["cblrs pseudo site site.yaml --key site.key --out pseudo-site.yaml"],
    "pseudo unmap": ["cblrs pseudo unmap pseudo-tracks.txt --key site.key --out tracks.txt"],
    "analytics": ["cblrs analytics tracks.txt --site sites/wildtrack.yaml --out analytics/"],
    "link": ["cblrs link --site street.yaml --plane 1=plane1.db --plane 2=plane2.db "
             "--plane 3=plane3.db --plane 4=plane4.db --out site-tracks.txt --analytics site/"],
    "broker-config": ["cblrs broker-config --out broker --cameras C1,C2,C3 --matchers matcher1 "
                      "--planes 1"],
    "up": ["cblrs up sites/wildtrack-live.yaml",
           "cblrs up sites/wildtrack-live.yaml --fast --until-done",
           "cblrs up sites/wildtrack-live.yaml --systemd units --container container"],
    "camera": ["cblrs camera --camera Camera1 --reference refs/Camera1.png --images "
               f"{MVX}/Image_subsets/C1 --fps 2 --detector onnx "
               "--model ../shared/models/yolox_nano.onnx"],
    "matcher": ["cblrs matcher --site site.yaml --db plane1.db --http 127.0.0.1:9100",
                "cblrs matcher --stats plane1.db"],
    "linker": ["cblrs linker --site street.yaml --db linker.db --backbone nats://n1:4222,"
               "n2:4222,n3:4222", "cblrs linker --stats linker.db"],
    "dashboard": ["cblrs dashboard --site site.yaml --db plane1.db --port 8080",
                  "cblrs dashboard --site site.yaml --users users.yaml --host 0.0.0.0 "
                  "--tls-cert dash.crt --tls-key dash.key"],
    "dashboard-users": ["cblrs dashboard-users add --users users.yaml alice --role admin",
                        "cblrs dashboard-users list --users users.yaml"],
    "dashboard-users add": ["cblrs dashboard-users add --users users.yaml alice --role admin",
                            "cblrs dashboard-users add --users users.yaml bob "
                            "--password-file bob.password"],
    "dashboard-users passwd": ["cblrs dashboard-users passwd --users users.yaml alice"],
    "dashboard-users set-role": ["cblrs dashboard-users set-role --users users.yaml bob admin"],
    "dashboard-users remove": ["cblrs dashboard-users remove --users users.yaml bob"],
    "dashboard-users list": ["cblrs dashboard-users list --users users.yaml --json"],
    "dashboard-users token": ["cblrs dashboard-users token --users users.yaml alice "
                              "--label grafana > grafana.token"],
    "dashboard-users revoke": ["cblrs dashboard-users revoke --users users.yaml alice "
                               "--label grafana"],
    "bench": ["cblrs bench lookup", "cblrs bench all --out bench-results"],
    "bench lookup": ["cblrs bench lookup --n 100000 --repeats 5"],
    "bench render": ["cblrs bench render --repeats 5"],
    "bench claims": ["cblrs bench claims --out bench-results"],
    "bench tracker": ["cblrs bench tracker --tracks 50,200 --cameras 4 --matchers fusion"],
    "bench pipeline": [f"cblrs bench pipeline --dataset {WT}"],
    "bench track": [f"cblrs bench track --dataset {WT} --repeats 5"],
    "bench camera": [f"cblrs bench camera --dataset {MVX}"],
    "bench detect": [f"cblrs bench detect --dataset {MVX}"],
    "bench analytics": ["cblrs bench analytics --tracks 200 --hours 1"],
    "bench linker": ["cblrs bench linker --planes 8 --people 50 --seconds 120"],
    "bench dashboard": ["cblrs bench dashboard --tracks 200 --seconds 20"],
    "bench backbone": ["cblrs bench backbone --backbones mosquitto,nats --cameras 10"],
    "bench asynchrony": ["cblrs bench asynchrony --spreads 5,20,50 --in-process-only"],
    "bench mqtt": ["cblrs bench mqtt --cameras 20 --fps 10 --runs matcher/paced "
                   "--paced-seconds 10"],
    "bench all": ["cblrs bench all --out bench-results"],
    "experiment": ["cblrs experiment targeting --out experiments"],
    "experiment targeting": ["cblrs experiment targeting --tracking plaza --out experiments"],
    "experiment resolution": ["cblrs experiment resolution --scenes plaza --out experiments"],
    "experiment calibration": [f"cblrs experiment calibration --dataset {WT} --out experiments"],
    "experiment counts": ["cblrs experiment counts --scenes wildtrack,plaza --out experiments"],
    "experiment tracking": ["cblrs experiment tracking --out experiments",
                            "cblrs experiment tracking --scenes roundabout,crowd --no-held-out"],
    "experiment planes": ["cblrs experiment planes --out experiments",
                          "cblrs experiment planes --seeds '' --people 20 --cars 6"],
    "experiment pseudo": [f"cblrs experiment pseudo --dataset {WT} --out experiments"],
}


class HelpFormatter(argparse.HelpFormatter):
    """Wraps descriptions, keeps the examples' line breaks, and shows each option's default
    where its help does not already say it."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("example"):
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (
            action.option_strings
            and "default" not in text
            and action.default not in (None, False, argparse.SUPPRESS)
            and not isinstance(action, argparse._HelpAction | argparse._VersionAction)
            and text is not argparse.SUPPRESS
        ):
            text += " (default: %(default)s)"
        return text


def decorate(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> None:
    """Give ``parser`` and every subcommand below it the help formatter and its examples."""
    parser.formatter_class = HelpFormatter
    examples = EXAMPLES.get(" ".join(path))
    if examples and not parser.epilog:
        parser.epilog = "example" + ("s" if len(examples) > 1 else "") + ":\n" + "\n".join(
            f"  {line}" for line in examples
        )
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                decorate(child, (*path, name))
