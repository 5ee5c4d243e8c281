"""Fusion tracker: repair after assignment, two people whose tracks swapped while they passed
close get their ids back (:mod:`cblrs.matching.fusion.swaps`)."""

from __future__ import annotations

import json

import numpy as np

from cblrs.detections import CLASS_NAMES
from cblrs.matching import kalman
from cblrs.matching.fusion import FusionConfig, NoiseModel
from cblrs.matching.fusion.swaps import SwapCheck
from cblrs.matching.fusion.table import FusionContext, TrackTable

PERSON = CLASS_NAMES.index("person")
FPS = 10.0


def stage(**options) -> SwapCheck:
    config = FusionConfig(**options)
    context = FusionContext(
        config,
        ["a", "b"],
        np.full((2, 2), np.nan),
        np.zeros(len(CLASS_NAMES) + 1),
        np.ones(len(CLASS_NAMES) + 1),
        NoiseModel(0.2, 0.03),
    )
    return SwapCheck(context, np.full(len(CLASS_NAMES) + 1, config.acceleration_sigma))


def crossing(seconds: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """Times and (F, 2, 2) positions of two people crossing at right angles: one walks east,
    the other north, both at 1.2 m/s, at the origin together at 2.5 s."""
    times = np.arange(int(seconds * FPS)) / FPS
    east = np.column_stack([-3.0 + 1.2 * times, np.zeros_like(times)])
    north = np.column_stack([np.zeros_like(times), -3.0 + 1.2 * times])
    return times, np.stack([east, north], axis=1)


def table(state, covariance, probability, ids=(4, 9)) -> TrackTable:
    count = len(ids)
    combined, combined_covariance = kalman.combine(state, covariance, probability)
    return TrackTable(
        ids=np.asarray(ids, np.int64),
        class_id=np.full(count, PERSON, np.int64),
        state=combined,
        covariance=combined_covariance,
        mode_state=state.copy(),
        mode_covariance=covariance.copy(),
        mode_probability=probability.copy(),
        evidence=np.full(count, 10),
        last_seen=np.zeros(count),
        seen_by=np.zeros((count, 2)),
        velocity_sigma=np.full(count, 0.1),
        heading=np.zeros((count, 2)),
        heading_time=np.full(count, -np.inf),
        heading_sigma=np.zeros(count),
    )


def track(
    check: SwapCheck,
    swap_at: float | None,
    restore_at: float | None = None,
    seed: int = 0,
    nudge_at: float | None = None,
) -> list[tuple[float, list[tuple[int, int]]]]:
    """Two tracks fed each instant with one person's views, as the tracker would, each
    following the other person from ``swap_at`` on (None: never); the stage's decisions.
    ``restore_at``: the stage is rebuilt from its saved state (as JSON) at that time;
    ``nudge_at``: the first track's filter moves by a millimetre then (as another stage of
    the tracker could move it), after its update."""
    rng = np.random.default_rng(seed)
    times, people = crossing()
    config = check.context.config
    models = len(config.model_sojourn_s)
    sigma = config.acceleration_sigma * np.asarray(config.model_acceleration_factors)
    view = (0.08**2 + config.object_sigma_m**2) * np.eye(2)
    start = np.zeros((2, models, 4))
    start[:, :, :2] = people[0][:, None]
    start[0, :, 2], start[1, :, 3] = 1.2, 1.2
    covariance = np.tile(np.diag([0.05, 0.05, 0.05, 0.05]), (2, models, 1, 1))
    probability = np.tile(kalman.stationary_probability(np.asarray(config.model_sojourn_s)), (2, 1))
    state = start
    ids = np.array([4, 9])
    decisions = []
    for index, now in enumerate(times):
        if index:
            state, covariance, probability = kalman.predict_models(
                state,
                covariance,
                probability,
                now - times[index - 1],  # the tracker's step: between timestamps
                np.tile(sigma, (2, 1)),
                np.asarray(config.model_sojourn_s),
            )
        seen = people[index] + rng.normal(0.0, 0.08, (2, 2))
        if swap_at is not None and now >= swap_at:
            seen = seen[::-1]
        state, covariance, probability = kalman.update_models(
            state, covariance, probability, seen, np.stack([view, view])
        )
        if nudge_at is not None and abs(now - nudge_at) < 1e-9:
            state = state.copy()
            state[0, :, 0] += 0.001
        rows = table(state, covariance, probability, ids)
        if restore_at is not None and abs(now - restore_at) < 1e-9:
            saved = json.loads(json.dumps(check.get_state()))
            check = stage(
                **{
                    name: getattr(config, name)
                    for name in ("swap_radius_m", "swap_settle_s", "swap_margin")
                }
            )
            check.set_state(saved)
        check.observe(rows.ids, seen, np.stack([view, view]), np.ones(2, dtype=bool))
        swaps = check.decide(rows, float(now))
        for first, second in swaps:
            ids[first], ids[second] = ids[second], ids[first]
        decisions.append((float(now), swaps))
    return decisions


def swapped(decisions) -> list[float]:
    return [now for now, swaps in decisions if swaps]


def test_tracks_that_swapped_at_a_crossing_get_their_ids_back_once_apart():
    decisions = track(stage(), swap_at=2.5)
    # The people are 1 m apart at 2.9 s; the tracks, their filters turning after the wrong
    # views, a little later; 0.5 s after that the stage decides, once.
    assert len(swapped(decisions)) == 1
    assert 3.4 <= swapped(decisions)[0] <= 4.0


def test_tracks_that_kept_their_people_are_not_swapped():
    for seed in range(5):
        assert swapped(track(stage(), swap_at=None, seed=seed)) == []


def test_off_when_swap_radius_m_is_zero():
    check = stage(swap_radius_m=0.0)
    assert swapped(track(check, swap_at=2.5)) == []
    assert check.open_count == 0


def test_a_restored_stage_continues_its_open_encounter():
    # Saved while the two are together (the encounter open), restored, it decides alike.
    assert swapped(track(stage(), swap_at=2.5, restore_at=2.7)) == swapped(
        track(stage(), swap_at=2.5)
    )


def gains(monkeypatch, **options) -> list[tuple[float, float, int]]:
    """Each decision's gain as the stage took it and as replayed from its records, and the
    encounter's serial (-1: the stage replayed it too)."""
    taken: list[tuple[float, float, int]] = []
    online = SwapCheck._gain

    def both(self, encounter, key, class_id):
        gain = online(self, encounter, key, class_id)
        taken.append((gain, self.swap_gain(encounter, key, class_id), encounter.serial))
        return gain

    monkeypatch.setattr(SwapCheck, "_gain", both)
    track(stage(), **options)
    return taken


def test_the_runs_advanced_each_instant_give_the_replayed_gains(monkeypatch):
    # Equal within float summation noise: the two paths run the same filters on batches of
    # other sizes, and BLAS may order a product's terms by batch size (they were equal bit
    # for bit with one numpy build and 4e-15 apart with another). A decision is a margin of
    # 7 log units: 1e-9 cannot move one.
    for options in ({"swap_at": 2.5}, {"swap_at": None, "seed": 1}):
        taken = gains(monkeypatch, **options)
        assert taken
        assert all(serial >= 0 for _, _, serial in taken)
        assert all(abs(gain - replayed) <= 1e-9 * max(1.0, abs(replayed))
                   for gain, replayed, _ in taken)


def test_an_encounter_whose_filter_another_stage_moved_is_replayed(monkeypatch):
    # The nudged track's filter is no longer its run through its own views: the stage
    # notices (one step from the instant before) and replays that encounter when decided.
    replays = []
    replayed = SwapCheck.swap_gain

    def counted(self, encounter, key, class_id):
        replays.append(encounter.serial)
        return replayed(self, encounter, key, class_id)

    monkeypatch.setattr(SwapCheck, "swap_gain", counted)
    decisions = track(stage(), swap_at=2.5, nudge_at=2.6)
    assert replays and set(replays) == {-1}
    assert len(swapped(decisions)) == 1
