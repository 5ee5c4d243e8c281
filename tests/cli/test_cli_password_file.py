"""A broker password file others can read works, with a warning that names the fix."""

from __future__ import annotations

import argparse
import logging

from cblrs.cli.mqtt_options import read_password


def test_a_password_file_others_can_read_is_warned_about(tmp_path, caplog):
    secret = tmp_path / "camera.password"
    secret.write_text("s3cret\n")
    secret.chmod(0o644)
    arguments = argparse.Namespace(password_file=secret, username="camera")
    with caplog.at_level(logging.WARNING, logger="cblrs.cli.mqtt_options"):
        assert read_password(arguments) == "s3cret"
    assert "readable by other users" in caplog.text and "chmod 600" in caplog.text
    assert "0644" in caplog.text
    caplog.clear()
    secret.chmod(0o600)
    with caplog.at_level(logging.WARNING, logger="cblrs.cli.mqtt_options"):
        assert read_password(arguments) == "s3cret"
    assert caplog.text == ""
