"""The options of ``cblrs matcher --http``: where to serve the metrics, and the token that
guards them beyond loopback (docs/security.md, "Matcher metrics")."""

from __future__ import annotations

import argparse
from pathlib import Path

from cblrs.cli.common import InputError, UsageError

MIN_TOKEN_CHARS = 16


def add_http_options(group: argparse._ArgumentGroup) -> None:
    """Add ``--http`` and ``--http-token-file`` to ``group``."""
    group.add_argument(
        "--http",
        metavar="HOST:PORT",
        help="serve Prometheus /metrics, /healthz and /readyz here (e.g. 127.0.0.1:9100; "
        "beyond loopback only with --http-token-file)",
    )
    group.add_argument(
        "--http-token-file",
        type=Path,
        metavar="FILE",
        help="/metrics needs this token (first line of FILE), as a bearer token or the "
        "basic-auth password; health checks from loopback do not (docs/security.md)",
    )


def http_settings(args: argparse.Namespace) -> tuple[tuple[str, int], str | None]:
    """``(host, port)`` and the token of ``--http``; a usage error for metrics beyond
    loopback without a token, or a token too short to be one."""
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.runtime.matcher.metrics import is_loopback_host, parse_address

    address = parse_address(args.http)
    token = _read_token(args.http_token_file)
    if token is None and not is_loopback_host(address[0]):
        raise UsageError(
            f"--http {args.http} serves the metrics beyond this machine, so it needs "
            "--http-token-file FILE; without it, serve on 127.0.0.1."
        )
    return address, token


def _read_token(path: Path | None) -> str | None:
    if path is None:
        return None
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read --http-token-file {path}: "
                         f"{getattr(error, 'strerror', None) or error}.") from None
    token = lines[0].strip() if lines else ""
    if len(token) < MIN_TOKEN_CHARS:
        raise UsageError(f"--http-token-file {path} holds a token of {len(token)} characters; "
                         f"give at least {MIN_TOKEN_CHARS} (e.g. python -c 'import secrets; "
                         "print(secrets.token_urlsafe(32))').")
    return token
