"""The spool remembers, across runs, which sequences it has handed to a transport: a replay
restarted from its beginning produces them again, and on NATS their first ids are taken."""

from __future__ import annotations

from cblrs.runtime.camera.spool import Spool


def test_the_sequences_handed_over_are_remembered_across_runs(tmp_path):
    path = tmp_path / "camera.db"
    with Spool(path) as spool:
        assert spool.handed_before == 0
        for sequence in range(5):
            assert spool.append(sequence, "cblrs/1/c/detections", b"x%d" % sequence)
        assert [item[0] for item in spool.take(3)] == [0, 1, 2]
        spool.confirm([0, 1])
    with Spool(path) as spool:
        assert spool.handed_before == 3  # 0 and 1 confirmed (gone), 2 handed: all below 3
        assert [item[0] for item in spool.take(10)] == [2, 3, 4]
    with Spool(path) as spool:
        assert spool.handed_before == 5
    assert Spool(None).handed_before == 0
