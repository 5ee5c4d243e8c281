"""The fusion tracker: one observation per object per instant, Kalman-tracked on the ground.

Where the paper's matcher compares every detection with every object, camera by camera,
this tracker uses what the colour code makes possible: every camera's detections land in
the same metric ground frame, so the views of one person at one instant are noisy
observations of one point. Per instant:

1. decode all colours to world positions (metres); give each detection a covariance
   elongated along the ray from its camera (a box edge's pixel error moves a foot point
   along the viewing direction far more than across it) and remove the learned along-ray
   bias; move a vehicle's detection along its ray from where its box's target pixel
   landed to its footprint centre (:mod:`~cblrs.matching.fusion.footprint`: by the
   class's size, averaged over headings, and by its track's heading once it has one);
2. predict every track to the instant with an interacting multiple-model filter: two
   constant-velocity Kalman filters, one steady and one manoeuvring (white-noise
   accelerations of a quarter of and twice the class's: a person walking straight
   hardly accelerates, one turning or stopping does), weighed
   by how well each has been predicting;
3. associate: groups of precise detections are assigned across cameras as one observation;
   the rest camera by camera, most precise camera first, each against the tracks as
   corrected by the cameras before it (as a Kalman filter processes independent sensors),
   then once more against the tracks corrected by all other cameras. Each step is a
   Hungarian assignment on the negative log-likelihood, gated by Mahalanobis distance,
   a metric cap, class, and for a moving vehicle its reachable cone (a car neither
   reverses nor jumps across the road; a track takes at most one detection from each camera). An
   early wrong choice propagates to the cameras after it, so where tracks compete the
   cameras are assigned again in the reverse order, and each connected group of tracks
   and detections where the two assignments differ keeps the more likely one (the sum of
   the cameras' innovation costs, an unassigned detection costing as much as one at the
   gate); detections scoring below ``high_confidence`` are associated after the others,
   and a track keeps them only with a second view (they never start a track alone);
4. let leftovers join a track other cameras saw at this instant when they are consistent
   with its fused position (the gate must not split one object's views); then release the
   detections of a vehicle track that would have had to turn tighter than its class can
   (the motion check: a coasting car must not take the next car on the opposite lane; the
   fused position is tested against the cone in its noise across the cone's edge, and a
   track whose velocity a wrong view threw off is still held to its last well-known motion);
5. fuse each track's detections in information form (inverse covariances) and update the
   filter once, adding an object-level noise common to all views; a vehicle whose views were
   refined with its heading is reported where those views put it under their own learned
   noise (:mod:`~cblrs.matching.fusion.vehicle_noise`; the filter keeps the class's wider
   noise, which association needs);
6. cluster the remaining detections across cameras (at most one per camera per cluster,
   complete linkage on the Mahalanobis distance) and start a tentative track per cluster;
7. confirm tracks with enough evidence (camera detections; where two cameras see the
   ground, from both: multi-view confirmation), split vehicle tracks whose direction turned
   further than they can turn, optionally merge duplicates, delete tracks unseen for too
   long or that left the planes; a track about to be confirmed that continues one deleted
   for being unseen too long (both moving, alike in position where they meet and in
   velocity, and no other pair could be it) takes that track's id instead of a new one
   (stitching: decided at confirmation, no id ever rewritten); two people whose tracks
   came within a metre exchange ids once they are apart again if each track's motion before
   the encounter explains the other's views after it far better (swaps: decided half a
   second after they part, from then on); report the confirmed tracks
   seen now, and, once the cameras are known to miss the people nearer ones hide, a person
   missed by every camera whose every covering view has someone right in front of them
   (hidden, for at most ``report_hidden_s``); a track that the other cameras covering its
   place keep not seeing, not moving, is neither confirmed nor reported (support: a
   detector's persistent false positive).

Cameras need not be synchronised. Messages are fused in windows of nearby capture times
(:mod:`cblrs.matching.timing`: a fraction of the shortest frame period wide, one message per
camera, released once no camera can still add to it), each detection at its own capture time:
its gate is widened by how far its class moves in its lag to the window's latest time, and
once it has a track it is moved along the track's velocity to that time before fusion. Each
camera's clock offset is estimated from the data and subtracted from its timestamps
(:mod:`cblrs.matching.clock`): finely from how its views lead or trail the other cameras'
views of the same walking people, coarsely (seconds: a wrong clock) by searching the lag at
which its views land on the other cameras' tracks. A window is reported at the capture time
of each frame it holds, one row per confirmed track and frame.

Measurement noise is ``a**2 + (b * d)**2`` along the ray and ``e**2 + (c * d)**2`` across
it (``d`` the distance from the camera, along the ray scaled by the camera's height when
known), and :class:`NoiseModel` re-estimates the four coefficients and a bias online from
how much the cameras that see one object disagree, so the same defaults serve exact boxes
and a noisy detector. All parameters are physical (metres, seconds, m/s, m/s^2): the same
defaults serve 2 fps datasets and 10 or 20 fps video. Everything is online; there is no
look-ahead.

The package follows these steps: :mod:`~cblrs.matching.fusion.config` (parameters),
:mod:`~cblrs.matching.fusion.noise` (1), :mod:`~cblrs.matching.fusion.gaussian` (the Gaussian
algebra all steps share), :mod:`~cblrs.matching.fusion.association` (3, 4),
:mod:`~cblrs.matching.fusion.motion` (4, 7: vehicles' turns),
:mod:`~cblrs.matching.fusion.reachable` (3, 4: where a vehicle can be),
:mod:`~cblrs.matching.fusion.low_confidence` (3, 4: boxes below ``high_confidence``
only where a track seen by two cameras or another camera's sure view confirms them),
:mod:`~cblrs.matching.fusion.birth` (6, 7), :mod:`~cblrs.matching.fusion.coverage` (7: where
each camera sees), :mod:`~cblrs.matching.fusion.stitching` (7: new tracks continuing lost
ones), :mod:`~cblrs.matching.fusion.occlusion` (7: people hidden behind others),
:mod:`~cblrs.matching.fusion.support` (7: tracks the other covering cameras never see),
:mod:`~cblrs.matching.fusion.swaps` (7: people whose tracks swapped while close),
:mod:`~cblrs.matching.fusion.clocks` (camera clocks),
:mod:`~cblrs.matching.fusion.table` (what the stages share), :mod:`~cblrs.matching.fusion.state`
(snapshots) and :mod:`~cblrs.matching.fusion.tracker` (the tracker, which runs them: 2 and 5
are its own).
"""

from __future__ import annotations

from cblrs.matching.fusion.association import assign_per_camera
from cblrs.matching.fusion.birth import cluster_detections
from cblrs.matching.fusion.clocks import clock_report
from cblrs.matching.fusion.config import (
    DEFAULT_CLASS_ACCELERATION_SIGMA,
    DEFAULT_CLASS_MEASUREMENT_SIGMA_M,
    FusionConfig,
)
from cblrs.matching.fusion.gaussian import (
    close_pairs,
    fuse,
    inverse_cholesky_2x2,
    largest_sigma,
    mahalanobis_squared,
    ray_covariance,
)
from cblrs.matching.fusion.noise import NoiseModel
from cblrs.matching.fusion.state import STATE_VERSION
from cblrs.matching.fusion.tracker import FusionTracker

__all__ = [
    "DEFAULT_CLASS_ACCELERATION_SIGMA",
    "DEFAULT_CLASS_MEASUREMENT_SIGMA_M",
    "STATE_VERSION",
    "FusionConfig",
    "FusionTracker",
    "NoiseModel",
    "assign_per_camera",
    "clock_report",
    "close_pairs",
    "cluster_detections",
    "fuse",
    "inverse_cholesky_2x2",
    "largest_sigma",
    "mahalanobis_squared",
    "ray_covariance",
]
