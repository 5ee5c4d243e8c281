"""The dashboard's users file and `cblrs dashboard-users`: hashes, never passwords; the file
0600 and refused when others may write it; passwords never on the command line; the login
back-off; sessions that expire and end when the user's record changes (in-process, with a
clock the test moves)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys

import pytest

from cblrs.cli.main import main
from cblrs.dashboard.users import (
    Role,
    UsersError,
    UsersFile,
    hash_password,
    token_digest,
    verify_password,
)
from cblrs.names import name_problem


def users_command(*arguments: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    """`cblrs dashboard-users ...` (in this process, its standard input ``stdin``)."""
    saved = sys.stdin
    sys.stdin = io.StringIO(stdin or "")
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main(["dashboard-users", *arguments])
            except SystemExit as error:  # argparse's own usage errors
                code = int(error.code or 0)
    finally:
        sys.stdin = saved
    return subprocess.CompletedProcess(arguments, code, out.getvalue(), err.getvalue())


def test_password_hashes_are_salted_scrypt_and_verify():
    first, second = hash_password("correct horse battery"), hash_password("correct horse battery")
    assert first.startswith("scrypt$131072$8$1$") and first != second  # a salt each
    assert "correct horse" not in first
    assert verify_password("correct horse battery", first)
    assert not verify_password("correct horse batterY", first)
    for broken in ("", "plain-text"):
        assert not verify_password("correct horse battery", broken)
    with pytest.raises(UsersError, match="at least 10"):
        hash_password("short")


def test_users_file_is_private_and_holds_no_secret(tmp_path):
    path = tmp_path / "users.yaml"
    users = UsersFile.load(path, missing_ok=True)
    users.add("alice", Role.ADMIN, "alice-password-x")
    token = users.add_token("alice", "grafana")
    users.save()
    assert os.stat(path).st_mode & 0o777 == 0o600
    text = path.read_text()
    assert "alice-password-x" not in text and token not in text
    assert token_digest(token) in text
    loaded = UsersFile.load(path)
    assert loaded.find_token(token).name == "alice"
    assert loaded.find_token(token + "x") is None
    with pytest.raises(UsersError, match="exists already"):
        loaded.add("alice", Role.VIEWER, "another-password")
    with pytest.raises(UsersError, match="must not be the user name"):
        loaded.add("longusername", Role.VIEWER, "LongUserName")
    with pytest.raises(UsersError, match="user name"):
        loaded.add("<script>", Role.VIEWER, "another-password")
    os.chmod(path, 0o666)
    with pytest.raises(UsersError, match="writable by other users"):
        UsersFile.load(path)
    os.chmod(path, 0o600)
    path.write_text("version: 1\nusers:\n  eve: {role: admin, password: hunter2hunter2}\n")
    with pytest.raises(UsersError, match="not a scrypt hash"):
        UsersFile.load(path)


def test_dashboard_users_command(tmp_path):
    path = tmp_path / "users.yaml"
    password_file = tmp_path / "alice.password"
    password_file.write_text("alice-password-1\n")
    assert users_command("add", "--users", str(path), "alice", "--role", "admin",
                         "--password-file", str(password_file)).returncode == 0
    result = users_command("add", "--users", str(path), "bob", "--password-stdin",
                           stdin="bob-password-12\n")
    assert result.returncode == 0 and "added viewer bob" in result.stdout
    # No terminal and no password source: one sentence, exit 2, nothing written.
    result = users_command("add", "--users", str(path), "carol")
    assert result.returncode == 2 and "--password-stdin" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    # A password on the command line is not an option at all.
    result = users_command("add", "--users", str(path), "dave", "--password", "x" * 12)
    assert result.returncode == 2
    result = users_command("token", "--users", str(path), "alice", "--label", "ci")
    token = result.stdout.strip()
    assert result.returncode == 0 and token.startswith("cblrs_") and len(token) > 40
    listing = json.loads(users_command("list", "--users", str(path), "--json").stdout)
    assert listing == {"users": [
        {"name": "alice", "role": "admin", "password": True, "tokens": ["ci"]},
        {"name": "bob", "role": "viewer", "password": True, "tokens": []},
    ]}
    assert users_command("set-role", "--users", str(path), "bob", "admin").returncode == 0
    assert UsersFile.load(path).users["bob"].role == Role.ADMIN
    result = users_command("passwd", "--users", str(path), "nobody", "--password-stdin",
                           stdin="whatever-password\n")
    assert result.returncode == 2 and "no user 'nobody'" in result.stderr
    assert users_command("revoke", "--users", str(path), "alice", "--label", "ci").returncode == 0
    assert UsersFile.load(path).find_token(token) is None
    assert users_command("remove", "--users", str(path), "bob").returncode == 0
    assert list(UsersFile.load(path).users) == ["alice"]
    assert os.stat(path).st_mode & 0o777 == 0o600


@pytest.mark.parametrize(("name", "problem"), [
    ("north_gate", None),
    ("Entrée (nord) 2", None),
    ("St. Mary's gate", None),
    ("", "must not be empty"),
    (" gate", "must not start or end with a space"),
    ("x" * 65, "at most 64"),
    ('<img src=x onerror="alert(1)">', "may not contain '<'"),
    ("a&b", "may not contain '&'"),
    ('say "hi"', "may not contain '\"'"),
    ("tab\there", "U+0009"),
    ("zero\u200bwidth", "U+200B"),
])
def test_names_are_words_not_markup(name, problem):
    found = name_problem(name)
    assert (found is None) if problem is None else (problem in found), found
