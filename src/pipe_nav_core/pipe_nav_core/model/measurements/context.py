"""What every measurement shares: the epoch's context it reads, the settings indices, the
update kinds and event counters, and the one gated update it applies.

Frames: ENU navigation frame, base_link body frame (FLU). Units SI, angles rad.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numpy.typing import NDArray

from pipe_nav_core.filter.kalman import joseph_update
from pipe_nav_core.jit import kernel

if TYPE_CHECKING:
    from pipe_nav_core.filter.epoch import EpochOutputs

Array = NDArray[np.float64]
Index = NDArray[np.int64]
Model = tuple[Array, Array, Array]  # residual (m,), H (m, n), R (m, m)
Factor = tuple[str, Callable[[Array, Index], Model]]  # kind, model at a flat state and layout

# measurement kinds (rows of the update statistics)
KINDS = ("nhc", "odometer", "zupt", "zaru", "tilt", "mag", "marker")
K_NHC, K_ODO, K_ZUPT, K_ZARU, K_TILT, K_MAG, K_MARKER = range(7)
# event counters
COUNTERS = (
    "epochs",
    "epochs_without_odometer",
    "odometer_excluded",
    "tilt_gated_motion",
    "mag_disturbed",
)
C_EPOCHS, C_NO_ODO, C_EXCLUDED, C_TILT_GATED, C_MAG_DISTURBED = range(5)

# settings (prm, epoch.parameters)
P_EARTH_SIGN, P_PIPE_D, P_LEVER, P_LEVER_KNOWN = 0, 1, 2, 5  # P_LEVER: 3 values
P_STOP_SPEED, P_STOP_GYRO, P_ODO_SIGMA, P_NHC_SIGMA, P_ZUPT, P_ZARU = 6, 7, 8, 9, 10, 11
P_TILT_ON, P_TILT_GATE, P_TILT_SIGMA = 12, 13, 14
P_MAG_ON, P_MAG_NORM_GATE, P_MAG_DIP_GATE, P_MAG_DECL, P_MAG_SIGMA = 15, 16, 17, 18, 19
P_MAG_REF, P_MAG_DIP, P_MAG_REF_OK = 20, 21, 22
P_SCALE_RW, P_DR_ALONG, P_DR_LATERAL, P_MARKER_TIME = 23, 24, 25, 26
P_CHI2 = 27  # 3: gates for 1, 2, 3 rows
P_IMU = 30  # 6: process_noise_k's IMU densities
P_ARW = P_IMU  # gyro angle random walk, rad/sqrt(s)
P_SIZE = 36


@dataclass
class Measurement:
    """One update: name (for statistics), residual (m,), H (m, n), R (m, m)."""

    name: str
    residual: Array
    H: Array
    R: Array


class Context(NamedTuple):
    """One epoch as its measurements see it, after the prediction (built by
    :func:`pipe_nav_core.filter.epoch.context`).

    s: the flat state every update is linearized at; s1: the mechanized state at the epoch
    end; L: the layout (Layout.index); prm: the settings (P_*); T: the epoch's duration (s);
    speed: the raw mean odometer speed (m/s); stopped: the pig stands still; ins: the layout
    has a velocity error; odo_ok: the epoch has odometer data; excluded: its odometer speed is
    excluded (a slip); free: the heading is unanchored (its prior kept outside the filter);
    lever_rate: mean (omega x d)_x of the wheel contact (m/s); w_yz: the body's turn rate
    across the bore (rad/s); v_jac: the first-estimate Jacobian velocity (ENU m/s);
    mean_vel_b: the mean body velocity over the epoch (m/s); gyro_mean: the time-weighted mean
    gyro reading (rad/s, base_link); f_mean_n: mean C_nb (f - ba) (m/s^2); dp: the epoch's
    ENU displacement (m); sums: (3, 12) the sums of C_nb dt and C_nb[:, i] f_j dt over the
    epoch; has_prev_vel / prev_vel: the previous epoch's mean ENU velocity (m/s); imu_t / q:
    the epoch's sample times (s) and attitude quaternions; mag_i: its magnetometer sample
    (-1 none) into mag_t (s) / mag_f (T, base_link); markers: (M, 7) the marker passages to
    apply (:func:`marker.marker_vector`)."""

    s: Array
    s1: Array
    L: Index
    prm: Array
    T: float
    speed: float
    stopped: bool
    ins: bool
    odo_ok: bool
    excluded: bool
    free: bool
    lever_rate: float
    w_yz: float
    v_jac: Array
    mean_vel_b: Array
    gyro_mean: Array
    f_mean_n: Array
    dp: Array
    sums: Array
    has_prev_vel: bool
    prev_vel: Array
    imu_t: Array
    q: Array
    mag_i: int
    mag_t: Array
    mag_f: Array
    markers: Array


@kernel
def update(
    kind: int, r: Array, H: Array, R: Array, x: Array, P: Array, prm: Array, out: EpochOutputs
) -> None:
    """One gated update of (x, P) in place, counted under kind in out's statistics
    (epoch.EpochOutputs)."""
    m = r.shape[0]
    nis, dx, x_new, P_new = joseph_update(P, x, H, R, r, prm[P_CHI2 + m - 1])
    if dx.shape[0] == 0:
        out.rej[kind] += 1
        return
    x[:] = x_new
    P[:] = P_new
    out.acc[kind] += 1
    out.nis[kind] += nis
    out.dof[kind] += m


def factor(kind: int, model_k: Callable[..., Model], *args: object) -> Factor:
    """(the kind's name, its model at a flat state and layout): the kernel ``model_k`` called
    with (sv, L) and then ``args``, the inputs its measurement's policy chose."""
    return KINDS[kind], lambda sv, L: model_k(sv, L, *args)


@kernel
def rows(r: Array, H: Array, R: Array, lo: int, hi: int) -> Model:
    """Rows lo:hi of a measurement (residual, H, R), applied as an update of their own."""
    return r[lo:hi], H[lo:hi].copy(), R[lo:hi, lo:hi].copy()
