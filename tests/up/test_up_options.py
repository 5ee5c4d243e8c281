"""``cblrs up``'s bad options as an operator types them: one sentence, no traceback, exit 2
for a usage error (docs/cli.md) and 1 for a state folder it cannot make, nothing started."""

from __future__ import annotations

import pytest
from up_helpers import run_up


@pytest.mark.parametrize(("options", "code", "message"), [
    (["--speed", "0"], 2, "--speed must be a finite number greater than 0, got 0.0."),
    (["--speed", "nan"], 2, "--speed must be a finite number greater than 0, got nan."),
    (["--dashboard-port", "70000"], 2, "--dashboard-port must be 0..65535, got 70000."),
    (["--broker-port", "-1"], 2, "--broker-port must be 0..65535, got -1."),
    (["--status-interval", "nan"], 2, "--status-interval must be a positive number of seconds."),
    (["--stop-after", "-3"], 2, "--stop-after must be a positive number of seconds."),
    (["--out", "{tmp}/a-file"], 2, "--out {tmp}/a-file is a file; the state folder must be a "
     "folder (or a path that does not exist yet)."),
    (["--fast", "--speed", "2"], 2, "--speed paces replays and --fast replays them as fast "
     "as possible; give one or the other."),
    (["--run-as", "nosuchuser"], 2, "--run-as nosuchuser: there is no such user for Mosquitto "
     "to run as; create it (the Debian package creates mosquitto) or choose another."),
    (["--out", "{tmp}/a-file/state"], 1, "cannot make the state folder {tmp}/a-file/state "
     "(Not a directory); choose another --out."),
])
def test_a_bad_option_is_one_sentence_and_its_exit_code(small_site, tmp_path, options, code,
                                                        message):
    (tmp_path / "a-file").write_text("")
    options = [option.format(tmp=tmp_path) for option in options]
    exit_code, summary, err = run_up(small_site, tmp_path / "state", *options, timeout=60)
    assert (exit_code, summary) == (code, None), err
    assert "Traceback" not in err and err.strip().count("\n") == 0, err
    assert err.strip() == "cblrs up: error: " + message.format(tmp=tmp_path)
    assert not (tmp_path / "state").exists()
