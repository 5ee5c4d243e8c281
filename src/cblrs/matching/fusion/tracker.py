"""The fusion tracker: one observation per object per instant, Kalman-tracked on the ground.

:class:`FusionTracker` runs the steps of its update in order; each step lives in the module
named after it (the package docstring, :mod:`cblrs.matching.fusion`, describes them):
``noise`` (1, measurement noise), ``tracker`` (2, prediction; 5, the filter update),
``association`` (3, 4), ``birth`` (6, 7), ``stitching`` (7, new tracks continuing lost ones),
``occlusion`` (7, people hidden behind others), ``support`` (7, tracks the other covering
cameras never see), ``swaps`` (7, people whose tracks swapped), ``clocks`` (camera clocks),
``state`` (snapshots), ``vehicle_noise`` (5, where a vehicle refined by its heading is
reported). It stays one module a little over the size limit: what is left here is the order
of the stages and the filter's own prediction and update, which every stage's call sits in.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from cblrs.detections import CLASS_NAMES, CameraMessage, Tracks
from cblrs.matching import kalman
from cblrs.matching.base import (
    MatcherError,
    Observations,
    build_config,
    camera_index,
    decode_messages,
    require,
)
from cblrs.matching.clock import ClockModel
from cblrs.matching.fusion.association import Association
from cblrs.matching.fusion.birth import Births
from cblrs.matching.fusion.clocks import ClockLearning
from cblrs.matching.fusion.config import FusionConfig
from cblrs.matching.fusion.coverage import Coverage
from cblrs.matching.fusion.footprint import Footprint
from cblrs.matching.fusion.gaussian import camera_rays, fuse, ray_covariance
from cblrs.matching.fusion.low_confidence import LowConfidence, take_measured
from cblrs.matching.fusion.motion import MotionCheck
from cblrs.matching.fusion.noise import NoiseModel
from cblrs.matching.fusion.occlusion import Hidden
from cblrs.matching.fusion.state import STATE_VERSION, table_from_state, table_state
from cblrs.matching.fusion.stitching import Stitching
from cblrs.matching.fusion.support import Support
from cblrs.matching.fusion.swaps import SwapCheck
from cblrs.matching.fusion.table import FusionContext, Measured, TrackTable, largest_boxes
from cblrs.matching.fusion.vehicle_noise import VehicleNoise
from cblrs.matching.timing import Window, WindowBuffer
from cblrs.plane import PlaneSet

_PERSON = CLASS_NAMES.index("person")
_REPORTED_FRAMES = 64  # frames remembered to report each track at most once per frame


class FusionTracker:
    """Multi-camera fusion tracker (the default matcher).

    Args:
        planes: the planes the cameras' colours refer to.
        camera_ids: names of the cameras; a camera's index here is ``Tracks.camera_id``.
        **options: fields of :class:`FusionConfig`.

    Example:
        >>> from cblrs.plane import PlaneSet, PlaneSpec
        >>> tracker = FusionTracker(PlaneSet([PlaneSpec(1, (0, 0), 10, 10)]), ["a", "b"])
        >>> len(tracker.update(0.0, []))
        0
    """

    name = "fusion"

    def __init__(self, planes: PlaneSet, camera_ids: Sequence[str], **options: Any):
        self.config = build_config(FusionConfig, options, self.name)
        self.planes = planes if isinstance(planes, PlaneSet) else PlaneSet(planes)
        self.camera_ids = [str(name) for name in camera_ids]
        self._cameras = camera_index(self.camera_ids)
        self._camera_xy = np.full((len(self.camera_ids), 2), np.nan)
        # Along-ray distances are scaled by mean height / camera height when all placed
        # cameras have a height (1 otherwise).
        self._along_scale = np.ones(len(self.camera_ids))
        if self.config.camera_positions is not None:
            unknown = sorted(set(self.config.camera_positions) - set(self.camera_ids))
            require(not unknown, f"camera_positions names unknown camera(s): {unknown}.")
            heights = {}
            for name, position in self.config.camera_positions.items():
                self._camera_xy[self._cameras[name]] = position[:2]
                if len(position) == 3:
                    heights[self._cameras[name]] = position[2]
            if heights and len(heights) == len(self.config.camera_positions):
                index = np.array(list(heights))
                height = np.array(list(heights.values()))
                self._along_scale[index] = np.exp(np.mean(np.log(height))) / height
        config = self.config
        # Per class id (index into CLASS_NAMES; one extra slot for unknown ids).
        self._class_extra = np.array(
            [config.class_measurement_sigma_m.get(name, 0.0) for name in CLASS_NAMES] + [0.0])
        # Gate caps and cluster radii scale with the class's size relative to a person.
        self._class_scale = np.hypot(self._class_extra, config.measurement_sigma_m) / (
            config.measurement_sigma_m)
        self._class_acceleration = np.array(
            [config.class_acceleration_sigma.get(name, config.acceleration_sigma)
             for name in CLASS_NAMES] + [config.acceleration_sigma])
        self._windows = WindowBuffer(
            len(self.camera_ids), config.max_window_s, config.window_fraction)
        self._clock = ClockModel(
            len(self.camera_ids), config.clock_tolerance_s, config.max_clock_offset_s,
            estimate=config.estimate_clocks,
        )
        # What the stages share, and the stages themselves, called in order by _fuse_window.
        self.context = FusionContext(
            config, self.camera_ids, self._camera_xy, self._class_extra, self._class_scale,
            NoiseModel(config.measurement_sigma_m, config.along_sigma_per_distance,
                       config.sigma_per_distance, constant_bias=config.constant_bias),
        )
        self.association = Association(self.context)
        self.motion = MotionCheck(self.context)
        self.coverage = Coverage(self.planes, len(self.camera_ids))
        self.low_confidence = LowConfidence(self.context, self.association, self.coverage)
        self.hidden = Hidden(self.context, self.coverage)
        self.births = Births(self.context)
        self.footprint = Footprint.from_config(self.camera_ids, config)
        self.vehicle_noise = VehicleNoise(self.context, self.footprint.enabled)
        self.clock_learning = ClockLearning(self.context, self._clock)
        self.stitching = Stitching(self.context, self._class_acceleration)
        self.support = Support(self.context, self.coverage)
        self.swaps = SwapCheck(self.context, self._class_acceleration)
        self.reset()

    def reset(self) -> None:
        """Forget everything learnt or tracked: back to the state of a new instance."""
        self._time: float | None = None
        self._next_id = 1
        self.context.noise.reset()
        self.tracks = TrackTable.empty(self.context.models, len(self.camera_ids))
        self.measured = Measured.empty()
        self._windows.reset()
        self._clock.reset()
        self.clock_learning.reset()
        self.coverage.reset()
        self.stitching.reset()
        self.vehicle_noise.reset()
        self.hidden.reset()
        self.support.reset()
        self.swaps.reset()
        self._reported: dict[int, set[int]] = {}

    def get_state(self) -> dict:
        """The state as JSON-ready data, restored by :meth:`set_state`."""
        return {
            "version": STATE_VERSION,
            "camera_ids": list(self.camera_ids),
            "time": self._time,
            "next_id": self._next_id,
            "noise": self.context.noise.get_state(),
            **table_state(self.tracks),
            "windows": self._windows.get_state(),
            "clock": self._clock.get_state(),
            "reported": [[frame, sorted(ids)] for frame, ids in self._reported.items()],
            "clock_turn": self.clock_learning.turn,
            "coverage": self.coverage.get_state(),
            "stitching": self.stitching.get_state(),
            "vehicle_noise": self.vehicle_noise.get_state(),
            "hidden": self.hidden.get_state(),
            "swaps": self.swaps.get_state(),
        }

    def set_state(self, state: dict) -> None:
        """Restore a state saved by :meth:`get_state`."""
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise MatcherError(f"not a saved fusion-tracker state (expected {STATE_VERSION}).")
        if state.get("camera_ids") != self.camera_ids:
            raise MatcherError(
                f"the saved state is for cameras {state.get('camera_ids')}, "
                f"this tracker has {self.camera_ids}."
            )
        try:
            time = state["time"]
            self._time = None if time is None else float(time)
            self._next_id = int(state["next_id"])
            self.context.noise.set_state(state["noise"])
            self.tracks = table_from_state(state, self.context.models, len(self.camera_ids))
            self._windows.set_state(state["windows"])
            self._clock.set_state(state["clock"])
            self._reported = {int(frame): set(ids) for frame, ids in state["reported"]}
            self.clock_learning.turn = int(state["clock_turn"])
            self.coverage.set_state(state.get("coverage"))
            self.stitching.set_state(state.get("stitching"))
            self.vehicle_noise.set_state(state.get("vehicle_noise"))
            self.hidden.set_state(state.get("hidden"))
            self.swaps.set_state(state.get("swaps"))
        except (KeyError, TypeError, ValueError, IndexError) as error:
            raise MatcherError(f"the saved fusion-tracker state is incomplete: {error}.") from None

    def set_views(self, references: Sequence[Any]) -> None:
        """Tell the tracker which ground each camera sees, from its reference image.

        Multi-view confirmation (``confirm_cameras``) then knows where several cameras see
        the ground from the start, instead of learning it from their detections.

        Args:
            references: :class:`~cblrs.reference.ReferenceImage` or
                :class:`~cblrs.reference.OnDemandReference` objects whose ``camera_name``
                is one of this tracker's cameras (others are ignored).
        """
        for reference in references:
            camera = self._cameras.get(reference.camera_name)
            if camera is None:
                continue
            # Every 4th pixel each way: plenty for metre-sized cells (and an on-demand
            # reference renders only those, not the whole 16-bit frame).
            colours = reference.sampled_colours(4)
            located = [plane.decode_valid(colours) for plane in reference.planes]
            self.coverage.set_view(camera, np.concatenate(located))
            self.footprint.set_view(camera, reference)

    @property
    def track_count(self) -> int:
        """Live tracks, tentative ones included."""
        return len(self.tracks.ids)

    def update(self, timestamp: float, messages: Sequence[CameraMessage]) -> Tracks:
        """Take the messages of one released group and fuse every window now complete.

        Messages are fused in windows of nearby clock-corrected capture times (see
        :mod:`cblrs.matching.timing`), each at its own capture time, so the rows returned
        may belong to earlier groups, and a window waits until no message can still join it;
        :meth:`flush` fuses what waits at the end of a stream.

        Args:
            timestamp: every message captured (by the cameras' own clocks) at or before this
                has been delivered, in this call or earlier (the latest capture time among
                ``messages`` when groups are released in capture order), seconds.
            messages: messages from any subset of the cameras, each camera's in capture order.

        Returns:
            One row per confirmed track and fused window (frame: the window's newest frame).
        """
        for message in messages:
            camera = self._cameras.get(message.camera_id)
            if camera is None:
                raise MatcherError(
                    f"message from unknown camera {message.camera_id!r}; "
                    f"known: {', '.join(self._cameras)}."
                )
            self._windows.add(camera, message)
        self._windows.advance(float(timestamp))
        return self._drain(final=False)

    def flush(self) -> Tracks:
        """Fuse every message still waiting (the stream has ended); the rows of those windows."""
        return self._drain(final=True)

    def clock_report(self) -> dict[str, dict[str, Any]]:
        """Per camera: estimated clock offset (seconds, positive: ahead of the others), its
        uncertainty, whether it is beyond the tolerance, and counters (see
        :meth:`cblrs.matching.clock.ClockModel.report`)."""
        return self._clock.report(self.camera_ids)

    def clock_events(self) -> list[dict[str, Any]]:
        """Clock events since the last call: ``{"camera", "kind", "offset_s", "time_s"}``."""
        return [
            {"camera": self.camera_ids[event.camera], "kind": event.kind,
             "offset_s": event.offset_s, "time_s": event.time_s}
            for event in self._clock.events()
        ]

    @property
    def waiting(self) -> int:
        """Messages received but not fused yet (their window is not complete)."""
        return len(self._windows)

    def _drain(self, final: bool) -> Tracks:
        parts = []
        while (window := self._windows.next_window(self._clock.offsets, final)) is not None:
            parts.append(self._fuse_window(window))
        return parts[0] if len(parts) == 1 else Tracks.concatenate(parts)

    def _fuse_window(self, window: Window) -> Tracks:
        """Fuse one window: each message at its own corrected capture time."""
        times = window.times
        timestamp = float(times.max())
        if self._time is not None and timestamp < self._time:
            timestamp = self._time  # late messages are fused at the tracker's time
        fresh = times >= timestamp - self.config.max_lag_s
        for camera in window.cameras[~fresh].tolist():
            self._clock.stale(camera)
        if not fresh.all():
            window = Window([m for m, ok in zip(window.messages, fresh.tolist(), strict=True)
                             if ok], window.cameras[fresh], times[fresh], window.end)
            times = window.times
            if not len(times):
                return Tracks.empty()
        messages = window.messages
        # Capture time of each camera's message relative to the window's time (<= 0).
        lag_of_camera = np.zeros(len(self.camera_ids))
        lag_of_camera[window.cameras] = times - timestamp
        raw_time_of_camera = np.zeros(len(self.camera_ids))
        raw_time_of_camera[window.cameras] = [message.timestamp for message in messages]

        # 1. decode the colours; each detection's ray-shaped covariance (noise model).
        raw = decode_messages(self.planes, self._cameras, messages)
        lag = lag_of_camera[raw.camera]
        # 2. predict every track to the window's time.
        self._predict(timestamp)
        covariance = self._measurement_covariance(raw)
        base_covariance = covariance
        slot = FusionContext.class_slot(raw.class_id)
        if np.any(lag != 0):
            # Until a detection is given a track, its motion over its lag is unknown: widen
            # its gate by how far the class moves in that time.
            speed = self.context.class_velocity_sigma[slot]
            covariance = covariance + ((lag * speed) ** 2)[:, None, None] * (
                np.eye(2)[None])
        plain = self._class_extra[slot] == 0
        observed = raw
        if plain.any():
            # Box bottoms are not exactly the feet: remove the learned along-ray bias.
            shift = self.context.noise.bias(self.measured.distance,
                                            self.measured.along_distance)
            observed = dataclasses.replace(
                raw, world_xy=raw.world_xy - np.where(plain, shift, 0.0)[:, None]
                * self.measured.direction
            )
        # Vehicles: from the box target to the footprint centre, any heading (footprint module).
        observed = self.footprint.centre(observed, self.measured)

        # Where each camera locates things (coverage module, for multi-view confirmation),
        # from the detections it is sure of.
        high = self.low_confidence.is_high(observed)
        self.coverage.learn(observed.world_xy[high], observed.camera[high])
        # 3. associate, high-confidence detections first (low_confidence and association
        # modules); 4. leftovers join tracks seen at this instant.
        assigned = self.low_confidence.associate(self.tracks, self.measured, observed,
                                                 covariance, timestamp)
        # 4b. vehicles cannot turn on the spot (motion module).
        assigned = self.motion.check(self.tracks, observed, covariance, assigned, timestamp)
        # 4c. low-confidence detections neither a multi-view track nor another camera's
        # sure view confirms are dropped: no filter, noise model, clock or birth sees them.
        kept = self.low_confidence.kept(self.tracks, observed, covariance, assigned)
        if not kept.all():
            raw, observed = raw[kept], observed[kept]
            covariance, base_covariance = covariance[kept], base_covariance[kept]
            lag, plain, assigned = lag[kept], plain[kept], assigned[kept]
            self.measured = take_measured(self.measured, kept)
        observed = self.footprint.refine(observed, self.measured, self.tracks, assigned)  # 4d
        refined = self.vehicle_noise.refined(self.tracks, observed.class_id, assigned)
        matched = assigned >= 0
        located_xy = observed.world_xy
        if matched.any() and np.any(lag[matched] != 0):
            # Each view shows its track where it was at the view's capture time: move it
            # along the track's velocity to the window's time.
            rows = assigned[matched]
            motion = lag[matched, None] * self.tracks.state[rows, 2:4]
            observed = dataclasses.replace(observed, world_xy=observed.world_xy.copy())
            observed.world_xy[matched] -= motion
            raw = dataclasses.replace(raw, world_xy=raw.world_xy.copy())
            raw.world_xy[matched] -= motion
            covariance = base_covariance.copy()
            covariance[matched] += (lag[matched] ** 2)[:, None, None] * (
                self.tracks.covariance[rows, 2:4, 2:4])
        if self.config.adapt_noise:
            self.context.noise.learn(raw.world_xy, self.measured.distance,
                                     np.where(plain, assigned, -1), self.measured.direction,
                                     self.measured.along_distance)
            self.vehicle_noise.learn(observed.world_xy, self.measured, refined, assigned,
                                     observed.class_id)
        # 5. fuse each track's views and update its filter once.
        seen_now, report_camera, report_box, cameras_of_track = self._update_tracks(
            observed, covariance, base_covariance, assigned, timestamp, refined)

        self.hidden.learn(self.tracks, seen_now, observed, self.measured, assigned)  # occlusion
        # Which cameras saw each track, of those that could have (support module).
        self.support.learn(self.tracks, seen_now, cameras_of_track, window.cameras, timestamp)
        # 6. births from clusters of what no track took (birth module).
        born = self.births.birth(observed[~matched], covariance[~matched], timestamp)
        self.tracks = self.tracks.extend(born.tracks)
        seen_now = np.concatenate([seen_now, np.ones(len(born.tracks), dtype=bool)])
        report_camera = np.concatenate([report_camera, born.camera])
        report_box = np.concatenate([report_box, born.box])
        cameras_of_track = np.concatenate([cameras_of_track, born.cameras])

        # 7. merge duplicates, drop tracks unseen too long (the stitching stage keeps those
        # another track may continue), confirm, report.
        keep = self.births.merge_duplicates(self.tracks, seen_now, cameras_of_track)
        aged, departed = self._ended(timestamp, seen_now)
        self.stitching.remember(self.tracks.select(keep & aged & ~departed), timestamp)
        if not (keep := keep & ~(aged | departed)).all():  # (rebuilt only when a track goes)
            self.tracks, seen_now = self.tracks.select(keep), seen_now[keep]
            report_camera, report_box = report_camera[keep], report_box[keep]

        # A vehicle track that turned further than it can is another vehicle from now on.
        turned = self.motion.split(self.tracks, seen_now, timestamp) & (self.tracks.ids >= 0)
        if turned.any():
            count = int(turned.sum())
            self.tracks.ids[turned] = self._next_id + np.arange(count)
            self._next_id += count
        # A new track that continues a lost one takes its id (stitching module).
        # Tracks the other covering cameras never see (support module) are not confirmed,
        # nor reported.
        unsupported = self.support.unsupported(self.tracks)
        confirmable = self._confirmable(timestamp) & ~unsupported
        # Coasting people may be continued too where cameras lose people who are still there.
        coasting = ~seen_now & (self.tracks.class_id == _PERSON) & (self.hidden.miss_rate > 0.5)
        stitches = self.stitching.decide(self.tracks, confirmable, timestamp, coasting)
        confirmable &= ~stitches.hold
        confirmable[stitches.rows] = False
        self.tracks.ids[stitches.rows] = stitches.ids
        if len(stitches.replaced):  # the coasting tracks a new one continues: gone
            keep = np.ones(len(self.tracks.ids), dtype=bool)
            keep[stitches.replaced] = False
            self.tracks, seen_now, confirmable = (
                self.tracks.select(keep), seen_now[keep], confirmable[keep])
            report_camera, report_box = report_camera[keep], report_box[keep]
            unsupported = unsupported[keep]
        report = self._confirm(timestamp, seen_now, confirmable)
        for pair in self.swaps.decide(self.tracks, timestamp):  # swapped people (swaps module)
            self.tracks.ids[list(pair)] = self.tracks.ids[list(pair[::-1])]
        report |= self.hidden.missed(self.tracks, report, timestamp, observed, self.measured,
                                     matched)
        report &= ~unsupported
        self.clock_learning.record(self.tracks, timestamp, seen_now & (self.tracks.ids >= 0),
                                   located_xy, observed.camera, raw_time_of_camera)
        return self._report_instants(report, report_camera, report_box, window, timestamp)

    def _update_tracks(
        self, observed: Observations, covariance: np.ndarray, base_covariance: np.ndarray,
        assigned: np.ndarray, timestamp: float, refined: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Step 5: fuse each track's detections in information form and update its filter once.

        Returns per track: seen at this instant, the camera and box of its largest view (-1 /
        NaN when unseen), and which cameras saw it.
        """
        track_count = len(self.tracks.ids)
        seen_now = np.zeros(track_count, dtype=bool)
        report_camera = np.full(track_count, -1, np.int64)
        report_box = np.full((track_count, 4), np.nan)
        cameras_of_track = np.zeros((track_count, len(self.camera_ids)), dtype=bool)
        matched = assigned >= 0
        if matched.any():
            rows = assigned[matched]
            self.tracks.seen_by[rows, observed.camera[matched]] = timestamp
            self.clock_learning.learn(self.tracks, self.measured, observed, base_covariance,
                                      matched, rows, timestamp)
            fused_xy, fused_covariance, seen_now = fuse(
                rows, track_count, observed.world_xy[matched], covariance[matched])
            self.swaps.observe(self.tracks.ids, fused_xy,
                               fused_covariance + self.context.object_covariance, seen_now)
            # Vehicles refined by their heading: where they are, reported (vehicle_noise).
            self.tracks.located = self.vehicle_noise.locate(
                self.tracks, observed.world_xy, self.measured, refined,
                covariance - base_covariance, assigned, observed.class_id, timestamp)
            # The rows seen once as indices: a take per column costs less than a boolean
            # indexing, which counts the mask again each time (the same rows).
            seen = np.flatnonzero(seen_now)
            tracks = self.tracks
            (tracks.mode_state[seen], tracks.mode_covariance[seen],
             tracks.mode_probability[seen]) = kalman.update_models(
                tracks.mode_state[seen], tracks.mode_covariance[seen],
                tracks.mode_probability[seen], fused_xy[seen],
                fused_covariance[seen] + self.context.object_covariance)
            combined_state, combined_covariance = kalman.combine(
                tracks.mode_state[seen], tracks.mode_covariance[seen],
                tracks.mode_probability[seen])
            tracks.state[seen], tracks.covariance[seen] = combined_state, combined_covariance
            velocity_covariance = combined_covariance[:, 2:4, 2:4]
            tracks.seen_covariance[seen] = combined_covariance[:, :2, :2]
            tracks.velocity_sigma[seen] = np.sqrt(np.maximum(
                velocity_covariance[:, 0, 0] + velocity_covariance[:, 1, 1], 0.0))
            self.tracks.evidence += np.bincount(rows, minlength=track_count)
            self.tracks.last_seen[seen] = timestamp
            cameras_of_track[rows, observed.camera[matched]] = True
            report_camera, report_box = largest_boxes(observed, matched, rows, track_count)
        else:
            self._clock.corroboration(observed.camera, np.zeros(len(observed), dtype=bool))
        return seen_now, report_camera, report_box, cameras_of_track

    def _confirmable(self, timestamp: float) -> np.ndarray:
        """Step 7: (T,) bool, the tentative tracks with enough evidence to be confirmed."""
        tracks = self.tracks
        newly_confirmed = (tracks.ids < 0) & (tracks.evidence >= self.config.confirm_evidence)
        if self.config.confirm_cameras > 1 and newly_confirmed.any():
            # Multi-view confirmation: where several cameras see the ground, a track one
            # camera alone keeps seeing is more likely that camera's false positive.
            candidates = np.flatnonzero(newly_confirmed)
            cameras_seen = np.isfinite(tracks.seen_by[candidates]).sum(axis=1)
            covering = self.coverage.covering(tracks.state[candidates, :2])
            needed = np.clip(covering, 1, self.config.confirm_cameras)
            if self.config.confirm_moving_mps > 0:
                needed[tracks.clearly_moving(self.config.confirm_moving_mps, candidates)] = 1
            # A second camera's one coincidence does not confirm one camera's old track.
            lone = (needed > 1) & self.support.uncorroborated(tracks, candidates, timestamp)
            newly_confirmed[candidates[(cameras_seen < needed) | lone]] = False
        return newly_confirmed

    def _confirm(
        self, timestamp: float, seen_now: np.ndarray, newly_confirmed: np.ndarray
    ) -> np.ndarray:
        """Step 7: give new ids to the tracks ``newly_confirmed``; the mask of tracks to
        report (confirmed, and seen now or coasting briefly)."""
        count = int(newly_confirmed.sum())
        self.tracks.ids[newly_confirmed] = self._next_id + np.arange(count)
        self._next_id += count
        return (self.tracks.ids >= 0) & (
            seen_now | (timestamp - self.tracks.last_seen <= self.config.report_coasting_s)
        )

    def _report_instants(
        self, report: np.ndarray, report_camera: np.ndarray, report_box: np.ndarray,
        window: Window, timestamp: float,
    ) -> Tracks:
        """Rows of the reported tracks at each capture instant of the window.

        An instant is a frame number: the window's messages of one frame (cameras numbering
        frames alike, as data sets do) are one instant, at their mean corrected capture time;
        a window holding the frames of cameras at different rates reports each. The state is
        at the window's latest capture time and is moved back along the track's velocity.
        A track is reported at most once per frame: cameras whose clocks disagree by about
        a frame can put one frame's messages in two windows.
        """
        frame_list = [int(message.frame) for message in window.messages]
        distinct = sorted(set(frame_list))
        frames = np.asarray(frame_list, np.int64)
        parts = []
        for frame in distinct:
            reported = self._reported.get(frame)
            if reported is None:
                reported = self._reported[frame] = set()
                if len(self._reported) > _REPORTED_FRAMES:
                    del self._reported[next(iter(self._reported))]
            mask = report & ~np.isin(self.tracks.ids, list(reported)) if reported else report
            order = np.argsort(self.tracks.ids[mask], kind="stable")
            rows = np.flatnonzero(mask)[order]
            reported.update(self.tracks.ids[rows].tolist())
            instant = float(window.times[frames == frame].mean()) if len(distinct) > 1 else (
                float(window.times.mean()))
            position = self.vehicle_noise.position(self.tracks, rows, timestamp)
            if instant != timestamp:
                position = position + (instant - timestamp) * self.tracks.state[rows, 2:4]
            parts.append(Tracks(
                frame=np.full(len(rows), frame),
                timestamp=np.full(len(rows), instant),
                track_id=self.tracks.ids[rows],
                world_xy=position,
                camera_id=report_camera[rows],
                xyxy=report_box[rows],
                class_id=self.tracks.class_id[rows],
            ))
        return parts[0] if len(parts) == 1 else Tracks.concatenate(parts)

    def _predict(self, timestamp: float) -> None:
        if self._time is not None:
            # Messages of slightly different timestamps can arrive out of order; a late
            # one is treated as simultaneous rather than rewinding the filter.
            dt = max(0.0, timestamp - self._time)
            tracks = self.tracks
            if dt > 0 and len(tracks.ids):
                acceleration = self._class_acceleration[FusionContext.class_slot(tracks.class_id)]
                tracks.mode_state, tracks.mode_covariance, tracks.mode_probability = (
                    kalman.predict_models(
                        tracks.mode_state, tracks.mode_covariance, tracks.mode_probability, dt,
                        acceleration[:, None]
                        * np.asarray(self.config.model_acceleration_factors)[None],
                        np.asarray(self.config.model_sojourn_s),
                    )
                )
                tracks.state, tracks.covariance = kalman.combine(
                    tracks.mode_state, tracks.mode_covariance, tracks.mode_probability
                )
            self._time = max(self._time, timestamp)
        else:
            self._time = timestamp

    def _measurement_covariance(self, observed: Observations) -> np.ndarray:
        """(N, 2, 2) ground covariance of each detection, elongated along its camera's ray.

        Also sets ``measured`` (rays and the largest standard
        deviation of each detection, for neighbour searches).
        """
        distance, direction = camera_rays(observed.world_xy, self._camera_xy[observed.camera])
        along_distance = distance * self._along_scale[observed.camera]
        extra = self._class_extra[FusionContext.class_slot(observed.class_id)] ** 2
        along, lateral = self.context.noise.variances(distance, along_distance)
        # The model may learn that cameras agree closely; the floor keeps one camera from
        # being trusted without limit.
        floor = self.config.minimum_sigma_m**2
        along = np.maximum(along, floor) + extra
        lateral = np.maximum(lateral, floor) + extra
        self.measured = Measured(distance, along_distance, direction,
                                 np.sqrt(np.maximum(along, lateral)))
        return ray_covariance(direction, along, lateral)

    def _departed(self) -> np.ndarray:
        """(T,) bool: tracks predicted off every plane and moving away from the nearest.

        No camera can locate anything off the planes (the reference images end there): a
        track that is missed there while its velocity (as known when last seen, three
        standard deviations) points outwards has left the scene. Kept coasting, it would
        take the next object entering nearby (a car arriving on the opposite lane of the
        arm its own car left by). One standing at the border, whose views flicker on and
        off the plane, is not moving away and stays.
        """
        position, velocity = self.tracks.state[:, :2], self.tracks.state[:, 2:4]
        departed = np.ones(len(position), dtype=bool)
        for plane in self.planes:
            low = np.array(plane.origin, np.float64)
            high = low + np.array([plane.width, plane.length])
            outward = position - np.clip(position, low, high)
            distance = np.hypot(outward[:, 0], outward[:, 1])
            speed_out = np.einsum("ij,ij->i", velocity, outward) / np.maximum(distance, 1e-12)
            departed &= (distance > 0) & (speed_out > 3.0 * self.tracks.velocity_sigma)
        return departed

    def _ended(self, timestamp: float, seen_now: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(T,) bool each: tracks unseen too long, and tracks that left the located area."""
        age = timestamp - self.tracks.last_seen
        limit = np.where(self.tracks.ids >= 0, self.config.max_age_s,
                         self.config.tentative_max_age_s)
        departed = np.zeros(len(age), dtype=bool)
        if self.config.end_off_plane and len(age) and not seen_now.all():
            departed = ~seen_now & self._departed()
        return age > limit, departed

