"""The dashboard with a key shows a pseudo matcher's tracks and events on the real site."""

from __future__ import annotations

import asyncio
from dataclasses import replace
from pathlib import Path

import numpy as np

from cblrs.analytics import load_site_places
from cblrs.dashboard.feed import tracks_frame
from cblrs.dashboard.replay import StoreReplay
from cblrs.datasets import load_scene
from cblrs.privacy import PseudoKey, pseudo_places, tracks_to_pseudo
from cblrs.runtime.matcher.store import RuntimeStore
from cblrs.runtime.outputs.online_analytics import OnlineAnalytics
from cblrs.runtime.wire import decode_tracks, encode_tracks

KEY = PseudoKey(bytes(range(2, 34)), "00c0ffee")
EPOCH = 1_700_000_000.0
SITE = Path(__file__).resolve().parents[2] / "sites" / "wildtrack.yaml"


def test_replay_and_live_frames_map_pseudo_positions_back(wildtrack_root, tmp_path):
    truth = load_scene(wildtrack_root).ground_truth
    truth = truth[truth.frame <= 200]
    pseudo = tracks_to_pseudo(replace(truth, timestamp=truth.timestamp + EPOCH), KEY)
    places = load_site_places(SITE).places
    online = OnlineAnalytics(pseudo_places(places, KEY))
    store = RuntimeStore(tmp_path / "matcher.db")
    for t in np.unique(pseudo.timestamp):
        rows = pseudo[pseudo.timestamp == t]
        online.update(rows, t)
        store.commit_group([], rows, None, t, {}, also=online.take_writes())
    online.flush()
    store.commit_group([], pseudo[:0], None, float(pseudo.timestamp.max()), {},
                       also=online.take_writes())
    store.close()

    async def collect(replay):
        return [item async for item in replay.messages(speed=10.0)]

    shown = asyncio.run(collect(StoreReplay(tmp_path / "matcher.db", KEY.to_site)))
    rows = [row for item in shown if item["type"] == "tracks" for row in item["rows"]]
    assert len(rows) == len(truth)
    xy = np.array([[row[1], row[2]] for row in rows])
    assert np.abs(np.sort(xy, axis=0) - np.sort(truth.world_xy, axis=0)).max() < 0.01
    crossings = [item for item in shown if item["type"] == "event"
                 and item["kind"] == "line_crossed"]
    assert crossings
    for event in crossings:  # on the real line, where the map draws it
        line = places.line(event["place"])
        assert abs(line.signed_distance([event["world_xy"]])[0]) < 0.6
    # Without the key the same database is in pseudo space, far from the map.
    plain = asyncio.run(collect(StoreReplay(tmp_path / "matcher.db")))
    first = next(item for item in plain if item["type"] == "tracks" and item["rows"])
    assert abs(first["rows"][0][1]) > 20 or abs(first["rows"][0][2]) > 20
    # A live update is mapped the same way.
    update = decode_tracks(encode_tracks(pseudo[:5], 1))
    frame = tracks_frame(update, KEY.to_site)
    np.testing.assert_allclose([[row[1], row[2]] for row in frame["rows"]],
                               truth.world_xy[:5], atol=0.01)
