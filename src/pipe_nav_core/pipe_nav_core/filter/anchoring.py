"""The heading before and at its anchoring, and the recovery of a filter a marker contradicts.

With the heading from the markers, the live filter starts on a configured (or the survey's
bearing) azimuth and re-anchors it at the second marker by rotating its solution about the
vertical through the first (:func:`reanchor_heading`). Until then the
initial heading's prior is kept outside the filter (:class:`FreeHeading`). At every marker
passage a filter that disagrees with the surveyed marker beyond its gate has its predicted
covariance inflated until it agrees (:meth:`HeadingAnchor.before_marker`).
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.config import NavConfig
from pipe_nav_core.filter.kalman import ErrorStateKF
from pipe_nav_core.geo import attitude as att
from pipe_nav_core.geo import earth
from pipe_nav_core.model.measurements import marker, odometer
from pipe_nav_core.model.state import Layout, NavState
from pipe_nav_core.types import Marker

Array = NDArray[np.float64]

# rad: the live filter's own heading prior while its heading is unanchored; the rest of the
# configured prior is carried outside the filter as a rotation about the first marker (FreeHeading)
FREE_HEADING_SIGMA = math.radians(0.1)

# rad^2: the variance of an azimuth uniform over the circle
UNKNOWN_HEADING_VARIANCE = math.pi**2 / 3.0

# the share of rejected odometer speed updates since the last marker passage from which the
# filter has lost the wheel (clean runs: 1-3 %; the 100 km line at 2.5 Hz epochs after a
# 3.9 mrad pitch turn its simulated gyro did not show, before 0d6d5dc: 33 %, its velocity
# 6 mm/s^2 off and every speed update beyond the gate)
ODOMETER_LOST_FRACTION = 0.1
SPEED_KIND = odometer.KINDS[odometer.SPEED]  # the speed row's name in the update statistics


def _uniform_rotation_cov(d: Array) -> Array:
    """(..., 2, 2) second moments of (R(a) - I) d for horizontal vectors d (..., 2) and a
    uniform angle a: 1.5 d d^T + 0.5 d_perp d_perp^T (the error of a vector turned by an
    unknown heading)."""
    d = np.asarray(d, dtype=np.float64)
    perp = np.stack([-d[..., 1], d[..., 0]], axis=-1)
    return 1.5 * d[..., :, None] * d[..., None, :] + 0.5 * perp[..., :, None] * perp[..., None, :]


@dataclass(frozen=True)
class FreeHeading:
    """The part of the initial heading uncertainty that the live filter keeps outside its
    covariance until the heading is anchored at the second marker.

    Before the anchoring nothing the filter measures sees the heading (odometer, NHC, zero
    velocity and rate, tilt; the Earth rate's heading coupling is left out, epoch.py): an
    error of the initial heading rotates the whole solution about the vertical through the
    first marker and is never observed. Inside an EKF a prior of tens of degrees on such a
    direction is harmful: the gains computed from it are wrong at second order, and the
    heading wanders by tens of degrees on the way (27 degrees over 100 m on sag104). So the
    filter runs with FREE_HEADING_SIGMA, and the rest, a rotation angle of this variance, is
    added to what is reported (the Navigator's estimates, :meth:`variances`) and folded into
    the filter at the second marker before its fix. Linearly this equals carrying it inside.

    variance rad^2; lat, lon rad, h m: the pivot (first marker); until: s, the time of the
    anchoring (inf while unanchored); unknown: the heading is not known at all (markers as
    the heading source but fewer than two surveyed: the azimuth is the configured default),
    variance is then that of a uniform azimuth, UNKNOWN_HEADING_VARIANCE, and the reported
    covariances are those of a solution rotated by a uniform angle, not its linearization.
    """

    variance: float
    lat: float
    lon: float
    h: float
    until: float = math.inf
    unknown: bool = False

    def direction(self, lat: Array, lon: Array, h: Array, vel_n: Array, layout: Layout) -> Array:
        """(N, n) error-state direction (layout) of a unit rotation (rad) of the solution about
        the vertical through the pivot, at positions lat, lon rad, h m and velocities (N, 3)
        m/s ENU: attitude (0, 0, 1), velocity up x v, position up x (p - pivot)."""
        d = self._offset(lat, lon, h)
        v = np.asarray(vel_n, dtype=np.float64).reshape(-1, 3)
        g = np.zeros((len(d), layout.n))
        g[:, layout.att.start + 2] = 1.0
        if layout.vel is not None:
            g[:, layout.vel.start], g[:, layout.vel.start + 1] = -v[:, 1], v[:, 0]
        g[:, layout.pos.start], g[:, layout.pos.start + 1] = -d[:, 1], d[:, 0]
        return g

    def covariance(self, lat: float, lon: float, h: float, vel_n: Array, layout: Layout) -> Array:
        """(n, n) covariance (layout) this uncertainty adds to the estimate at lat, lon rad,
        h m with velocity vel_n m/s ENU."""
        if not self.unknown:
            g = self.direction(lat, lon, h, vel_n, layout)[0]
            return self.variance * np.outer(g, g)
        out = np.zeros((layout.n, layout.n))
        a = layout.att.start + 2
        out[a, a] = self.variance
        p = layout.pos.start
        out[p : p + 2, p : p + 2] = _uniform_rotation_cov(self._offset(lat, lon, h)[0, :2])
        if layout.vel is not None:
            v = layout.vel.start
            out[v : v + 2, v : v + 2] = _uniform_rotation_cov(np.asarray(vel_n)[:2])
        return out

    def variances(self, t: Array, lat: Array, lon: Array, h: Array) -> Array:
        """(N, 3) variances added to east, north (m^2) and azimuth (rad^2) at times t (s)."""
        d = self._offset(lat, lon, h)
        on = np.asarray(t, dtype=np.float64).reshape(-1) < self.until
        if self.unknown:
            c = _uniform_rotation_cov(d[:, :2])
            out = np.stack([c[:, 0, 0], c[:, 1, 1], np.full(len(d), self.variance)], axis=-1)
        else:
            out = self.variance * np.stack([d[:, 1] ** 2, d[:, 0] ** 2, np.ones(len(d))], axis=-1)
        return np.where(on[:, None], out, 0.0)

    def _offset(self, lat: Array, lon: Array, h: Array) -> Array:
        """(N, 3) ENU offsets (m) of positions lat, lon rad, h m from the pivot."""
        return earth.geodetic_to_enu(lat, lon, h, self.lat, self.lon, self.h).reshape(-1, 3)


def reanchor_heading(s: NavState, pivot: Marker, target: Marker) -> tuple[NavState, float]:
    """Rotate s about the vertical through ``pivot`` so that its horizontal displacement from
    ``pivot`` points at ``target``; returns the new state and the rotation (rad, azimuth
    increase). Position, velocity and attitude rotate together; biases are body-frame and stay.
    """
    here = earth.geodetic_to_enu(s.lat, s.lon, s.h, pivot.lat, pivot.lon, pivot.alt)
    goal = earth.geodetic_to_enu(
        target.lat, target.lon, target.alt, pivot.lat, pivot.lon, pivot.alt
    )
    if np.hypot(here[0], here[1]) < 1e-3 or np.hypot(goal[0], goal[1]) < 1e-3:
        return s, 0.0
    d_az = float(
        np.angle(np.exp(1j * (np.arctan2(goal[0], goal[1]) - np.arctan2(here[0], here[1]))))
    )
    rz = att.dcm_from_rotvec(np.array([0.0, 0.0, -d_az]))  # azimuth increase = rotation about -U
    new = s.copy()
    p = rz @ here
    lat, lon, h = earth.enu_to_geodetic(p, pivot.lat, pivot.lon, pivot.alt)
    new.lat, new.lon, new.h = float(lat), float(lon), float(h)
    new.vel_n = rz @ s.vel_n
    new.q_nb = att.quat_normalize(att.quat_mul(att.quat_from_rotvec([0.0, 0.0, -d_az]), s.q_nb))
    return new, d_az


class HeadingAnchor:
    """What a marker passage does to the filter before the epoch's updates (the re-anchoring,
    the free heading's return, the covariance inflation), and the heading's state: anchored
    (the heading no longer comes from the alignment alone), reanchor_rad (rad, the rotation
    applied at the anchoring), free_heading (the prior kept outside the filter, or None),
    inflated (the names of the markers whose passage inflated the covariance, in order) and
    after_odometer_loss (those of the markers the filter reached having rejected at least
    ODOMETER_LOST_FRACTION of its odometer speed updates since the passage before: its
    velocity had drifted off the wheel's, and a disagreement there is its own).

    counts: the navigator's counters, incremented here."""

    def __init__(self, config: NavConfig, layout: Layout, anchored: bool,
                 counts: defaultdict[str, int]) -> None:  # fmt: skip
        self.cfg = config
        self.layout = layout
        self.anchored = anchored
        self.reanchor_rad = 0.0
        self.free_heading: FreeHeading | None = None
        self.inflated: list[str] = []  # the markers whose passage inflated the covariance
        self.after_odometer_loss: list[str] = []  # the markers reached with the wheel lost
        self._counts = counts
        self._odometer = (0, 0)  # the speed updates accepted and rejected up to the last passage
        self._lost = False  # whether the filter had lost the wheel before the last passage

    def late(self, m: Marker, s: NavState) -> bool:
        """True (counted) for a marker passage too late for the epoch starting at s
        (marker.late)."""
        if marker.late(m, s.t):
            self._counts["late_marker_dropped"] += 1
            return True
        return False

    def before_marker(
        self, kf: ErrorStateKF, s: NavState, m: Marker, first: Marker | None
    ) -> tuple[NavState, Array]:
        """The heading re-anchoring at the second marker (heading from the markers; first: the
        first marker passed), and the recovery of a filter that has lost itself. A surveyed
        marker is the ground truth of this problem; when it disagrees with the prediction
        beyond the gate, the filter, not the marker, is wrong (accepted slips, a poor
        linearization): the predicted covariance is inflated until the marker is consistent
        (treated as extra process noise of this epoch, so that the smoother's record stays
        coherent) instead of rejecting the marker and diverging for good. kf is changed in
        place. Returns the state and the rotation applied to it (3, 3) (identity without
        re-anchoring)."""
        lay = self.layout
        rz = np.eye(3)
        later = first is not None and m.name != first.name
        free = self.free_heading
        if later and free is not None and free.until == math.inf:
            # the heading prior back into the filter (before a re-anchoring rotation)
            g = free.direction(s.lat, s.lon, s.h, s.vel_n, lay)[0]
            kf.P += free.variance * np.outer(g, g)
            self.free_heading = replace(free, until=s.t)
        if not self.anchored and first is not None and later:
            s, d_az = reanchor_heading(s, first, m)
            # the error state rotates with the nominal: nav-frame blocks of P turn with it
            rot = np.eye(lay.n)
            rz = att.dcm_from_rotvec(np.array([0.0, 0.0, -d_az]))
            for sl in (lay.att, lay.vel, lay.pos):
                if sl is not None:
                    rot[sl, sl] = rz
            kf.P = rot @ kf.P @ rot.T
            kf.x = rot @ kf.x
            self.anchored = True
            self.reanchor_rad = d_az
            self._counts["heading_reanchor_mdeg"] = int(round(math.degrees(d_az) * 1000))
        if self._odometer_lost(kf):
            self.after_odometer_loss.append(m.name)
        grow = marker.inflation(s, lay, m, kf.x, kf.P, time_sigma=self.cfg.marker_time_sigma,
                                gate_probability=self.cfg.gate_probability)  # fmt: skip
        if grow is not None:
            kf.P = kf.P * grow
            self._counts["marker_covariance_inflations"] += 1
            self.inflated.append(m.name)
        return s, rz

    def _odometer_lost(self, kf: ErrorStateKF) -> bool:
        """Whether the filter rejected ODOMETER_LOST_FRACTION or more of its odometer speed
        updates since the last marker passage (the same answer for passages of one epoch)."""
        done = (kf.stats.accepted[SPEED_KIND], kf.stats.rejected[SPEED_KIND])
        accepted, rejected = (a - b for a, b in zip(done, self._odometer, strict=True))
        if accepted + rejected:
            self._lost = rejected >= ODOMETER_LOST_FRACTION * (accepted + rejected)
        self._odometer = done
        return self._lost
