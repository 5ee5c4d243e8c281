"""``cblrs dashboard-users``: the dashboard's users file (add, passwd, set-role, remove,
list, token, revoke). Passwords are never given on the command line: they are typed at a
prompt, or read from a file or standard input."""

from __future__ import annotations

import argparse
import getpass
import json
import sys
from pathlib import Path
from typing import Any

from cblrs.cli.common import InputError, UsageError, add_output_options


def register(subparsers) -> None:
    """Add the ``cblrs dashboard-users`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "dashboard-users",
        help="the dashboard's users: add, passwd, set-role, remove, list, token, revoke",
        description=(
            "Keep the users file of `cblrs dashboard --users FILE`: each user has a role "
            "(viewer: sees the map, live and replay; admin: also calibrates) and a password "
            "stored as a scrypt hash, and may have API tokens (stored as SHA-256 hashes). "
            "Passwords are typed at a prompt (twice), or read from --password-file or "
            "--password-stdin; never from the command line. The file is written 0600. A "
            "running dashboard reads the change at once: a changed password, role or token "
            "ends that user's sessions."
        ),
    )
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)

    def action(name: str, help_text: str, password: bool = False) -> argparse.ArgumentParser:
        sub = actions.add_parser(name, help=help_text, description=help_text)
        sub.add_argument("--users", type=Path, required=True, metavar="FILE",
                         help="the users file (created by add)")
        if name != "list":
            sub.add_argument("name", help="the user's login name")
        add_output_options(sub)
        if password:
            source = sub.add_mutually_exclusive_group()
            source.add_argument("--password-file", type=Path, metavar="FILE",
                                help="read the password from the first line of FILE")
            source.add_argument("--password-stdin", action="store_true",
                                help="read the password from the first line of standard input")
        sub.set_defaults(handler=run)
        return sub

    add = action("add", "add a user (prompts for the password)", password=True)
    add.add_argument("--role", choices=["viewer", "admin"], default="viewer",
                     help="what the user may do")
    action("passwd", "set a user's password (ends their sessions)", password=True)
    role = action("set-role", "change a user's role (ends their sessions)")
    role.add_argument("role", choices=["viewer", "admin"])
    action("remove", "remove a user (ends their sessions)")
    action("list", "list the users, their roles and token labels")
    token = action("token", "make an API token for a user and print it once "
                   "(Authorization: Bearer TOKEN)")
    token.add_argument("--label", required=True, help="what the token is for, e.g. grafana")
    revoke = action("revoke", "revoke a user's API token")
    revoke.add_argument("--label", required=True, help="the token's label")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs dashboard-users`` with its parsed arguments; the exit code."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.dashboard.users import Role, UsersError, UsersFile

    try:
        users = UsersFile.load(args.users, missing_ok=args.action == "add")
        if args.action == "list":
            rows: list[dict[str, Any]] = [
                {"name": user.name, "role": user.role.label, "password": bool(user.password),
                 "tokens": [token.label for token in user.tokens]}
                for user in users.users.values()
            ]
            if args.json:
                print(json.dumps({"users": rows}, indent=2))
            else:
                for row in rows:
                    tokens = f", tokens: {', '.join(row['tokens'])}" if row["tokens"] else ""
                    print(f"{row['name']}: {row['role']}{tokens}")
            return 0
        if args.action == "add":
            users.add(args.name, Role.parse(args.role), _password(args, confirm=True))
            said = f"added {args.role} {args.name}"
        elif args.action == "passwd":
            users.get(args.name)  # an unknown user says so before the prompt
            users.set_password(args.name, _password(args, confirm=True))
            said = f"set the password of {args.name}"
        elif args.action == "set-role":
            users.set_role(args.name, Role.parse(args.role))
            said = f"{args.name} is now {args.role}"
        elif args.action == "remove":
            users.remove(args.name)
            said = f"removed {args.name}"
        elif args.action == "token":
            token = users.add_token(args.name, args.label)
            said = f"token {args.label!r} of {args.name}"
        else:
            users.revoke_token(args.name, args.label)
            said = f"revoked token {args.label!r} of {args.name}"
        users.save()
    except UsersError as error:
        raise UsageError(str(error)) from None
    if args.action == "token":
        # The token goes to stdout alone (for > FILE); it exists nowhere else.
        if args.json:
            print(json.dumps({"user": args.name, "label": args.label, "token": token}))
        else:
            print(token)
        if not args.quiet:
            print(f"cblrs dashboard-users: {said} written to {args.users}; it is shown only "
                  "now.", file=sys.stderr)
    elif args.json:
        print(json.dumps({"action": args.action, "user": args.name, "users": str(args.users)}))
    elif not args.quiet:
        print(f"{said} ({args.users})")
    return 0


def _password(args: argparse.Namespace, confirm: bool) -> str:
    """The password from --password-file, --password-stdin or a prompt (typed twice)."""
    if args.password_file is not None:
        try:
            lines = args.password_file.read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError) as error:
            raise InputError(f"cannot read --password-file {args.password_file}: "
                             f"{getattr(error, 'strerror', None) or error}.") from None
        return lines[0] if lines else ""
    if args.password_stdin:
        return sys.stdin.readline().rstrip("\r\n")
    if not sys.stdin.isatty():
        raise UsageError("no terminal to type the password at: give --password-file FILE or "
                         "--password-stdin.")
    password = getpass.getpass(f"password for {args.name}: ")
    if confirm and getpass.getpass("again: ") != password:
        raise UsageError("the two passwords differ; nothing changed.")
    return password
