"""What ``joint_oracle`` is told of the world: :class:`OracleWorld` (``[gnss_error]``, ``[scenario] start``,
``[inertial]``, the world's kinematics) and its own settings, with the layout of a vehicle's state block that
follows from them (docs/validation/oracle.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = ["GNSS_WORLDS", "OracleWorld"]

GNSS_WORLDS = ("white", "per_vehicle", "field", "satellites", "fix")


@dataclass(frozen=True)
class OracleWorld:
    """What the oracle is told of the world (``[gnss_error]``, ``[scenario] start``), plus its gate.

    Names and meanings as in ``couplers.sensing.gnss_error.GnssErrorParams`` (the oracle is in ``coloc`` and
    does not import ``couplers``: the runner copies the values)."""

    gnss: str = "white"  # "white" (no [gnss_error]), "per_vehicle" or "field"
    tau_s: float = 30.0
    common_share: float = 0.0
    common_tau_s: float = 600.0
    field_share: float = 0.0
    field_corr_length_m: float = 50.0
    field_tau_s: float = 300.0
    local_corr_length_m: float = math.inf  # "per_vehicle": no decorrelation by distance
    nlos: bool = False  # the world has NLOS episodes: gate the fixes
    # [inertial] (couplers/sensing/inertial.py): the accelerometer's turn-on and drift biases as states (None:
    # no [inertial], no bias states); the white noise density adds to model (1)'s driving noise.
    accel_turn_on_sigma: float | None = None
    accel_bias_sigma: float = 0.0
    accel_bias_tau_s: float = 300.0
    accel_noise_density: float = 0.0
    # Oracle settings (not the world's): the chi-square level of the NLOS gate, the consecutive exclusions
    # after which a fix is taken, the white share of the fix's variance, how long unseen features are kept.
    gate_level: float = 0.999
    max_exclusions: int = 40  # 30 s at 0.75 s: three mean episode lengths (10 s, the world's default)
    fix_noise_share: float = 1e-4
    feature_keep_s: float = 120.0
    # The world's field F as it draws it (couplers/sensing/gnss_error.py, FieldErrorProcess): its random Fourier
    # frequencies (M, 2) rad/m, F(p) = sum_m (cos(omega_m . p) a_m + sin(omega_m . p) b_m) / sqrt(M) per axis with
    # unit Gauss-Markov coefficients (field_tau_s). Given (the runner copies the world's draw), the oracle carries
    # the 4 M coefficients as shared states and the field is exact; None: the per-vehicle approximation above.
    field_omega: tuple | None = field(default=None, compare=False, repr=False)
    # The world's vehicle position is the front bumper and its heading the body axis (SUMO: getPosition, getAngle),
    # so while it turns at yaw rate w the bumper moves across the heading at about front_lever_m w besides the
    # velocity v = speed u(heading) (:func:`_front_slip`). 0: no such term (model (1) as the paper's).
    front_lever_m: float = 0.0
    # the per-step residual of that term, std front_slip_sigma_per_rad |w| Ts (m per rad turned), at most
    # front_slip_sigma_max_m (docs/validation/oracle.md, "Kinematics of the world")
    front_slip_sigma_per_rad: float = 2.5
    front_slip_sigma_max_m: float = 0.25
    # Sensor-frame rows: one heading error per vehicle and step shared by all its rows (exact joint term), rather
    # than independent per row.
    shared_heading: bool = True
    # Sensor-frame rows of a moving vehicle: its heading is the direction of its velocity state (the world's heading
    # is the velocity's direction, couplers/traffic/sumo.py), linearized at the predicted velocity (EKF), so the
    # heading error is the velocity state's, carried across steps. Rows of slow vehicles stay out (module docstring).
    heading_from_state: bool = True
    # Iterated EKF on the sensor-frame rows with heading_from_state: relinearized this many times at the posterior
    # velocity (0: one EKF update)
    heading_iterations: int = 0
    # heading_from_state rows also carry the heading's variance from the state's covariance as noise (conservative:
    # the heading's information is then counted once through H and its uncertainty once more in R)
    heading_row_inflation: bool = False
    # Diagnostic (docs/validation/oracle.md, ablations): False leaves the range-rate half of every sensor-frame row
    # out (heading_from_state and heading_state rows)
    range_rate_rows: bool = True
    # The IMU input of a moving vehicle rotated by the direction of its velocity state at t-1, linearized (EKF: the
    # input's dependence on that velocity enters the transition), rather than by a heading taken as independent noise.
    imu_heading_from_state: bool = True
    # First-estimate Jacobians (Huang, Mourikis & Roumeliotis 2010): the IMU input's Jacobian on the velocity at t-1
    # (imu_heading_from_state) taken at that velocity's first estimate, the prediction the sensor-frame rows of t-1
    # were linearized at, not at its posterior; the mean is propagated at the posterior.
    first_estimate_jacobians: bool = False
    # [inertial] gyroscope (couplers/sensing/inertial.py, its units: deg/s, deg/s/sqrt(Hz), s; None: not told). With
    # heading_state the heading and the gyroscope's bias (turn-on plus drift, a random walk of the drift's one-step
    # variance as for the accelerometer) are states per vehicle: the heading is predicted by the measured yaw rate
    # less the bias, the velocity is held along it by a constraint of std course_sigma_mps (the world's velocity is
    # the speed along the body axis, couplers/traffic/sumo.py; the std stands for what the model leaves out), and
    # the sensor-frame rows and the IMU input are linearized in it (module docstring of joint_oracle).
    gyro_turn_on_sigma: float | None = None
    gyro_bias_sigma: float = 0.0
    gyro_bias_tau_s: float = 1000.0
    gyro_noise_density: float = 0.0
    heading_state: bool = False
    course_sigma_mps: float = 0.1  # chosen on tuning seed 101 among 0.01, 0.1, 0.3 (docs/validation/oracle.md)
    # heading_state: the sensor-frame rows of a vehicle whose heading's linearization point is wider than this (deg,
    # one std) stay out, and a wide predicted heading is linearized at the velocity's direction when that is
    # narrower (:func:`coloc.methods.joint_oracle_rows._heading_linearization`); inf: every row in, at the mean.
    heading_row_max_std_deg: float = math.inf
    # With the field states: each fix also carries, as white noise, the field's increment between the predicted and
    # the true position (the exponential kernel's field is not smooth: 2 (1 - exp(-r / L)) of its variance over r,
    # r the predicted position's RMS error; :func:`coloc.methods.joint_oracle_rows._field_read_share`); False: the
    # field read at the predicted position as exact.
    field_read_noise: bool = False
    # "satellites" (couplers/sensing/gnss_satellites.py; the runner copies [gnss_error]): the satellites of the
    # constellation (S), their common errors' correlation time and sigmas (clock/orbit per satellite, vertical
    # ionosphere per satellite through the Klobuchar obliquity, one zenith troposphere through the SBAS mapping),
    # the receiver's own errors (code noise a^2 + b^2 / sin el, multipath (m / sin el)^2 correlated over the
    # distance travelled) and the Doppler noise. Each fix reads the shared states through its WLS gain
    # (Frame.oracle_gnss). A reflected signal's extra path 2 cos(el) D is told by its structure: D (m, the facade's
    # perpendicular distance times cos of the azimuth's angle to its normal) with mean nlos_d_mean_m and std
    # nlos_d_std_m (docs/validation/oracle.md, measured on a tuning seed's geometry), its rate by
    # 2 cos(el) |v| nlos_rate_share (std per m/s of speed).
    sv_count: int = 0
    sv_tau_s: float = 1800.0
    sv_clock_orbit_m: float = 0.5
    iono_vertical_m: float = 1.0
    tropo_zenith_m: float = 0.1
    code_noise_a_m: float = 0.3
    code_noise_b_m: float = 0.3
    multipath_m: float = 0.5
    multipath_corr_length_m: float = 10.0
    doppler_noise_mps: float = 0.05
    nlos_d_mean_m: float = 0.0
    nlos_d_std_m: float = 0.0
    nlos_rate_share: float = 0.0
    # the multipath part of each fix as a per-vehicle state correlated over the distance travelled (False: white)
    multipath_state: bool = True
    # "fix" (the satellite world told at fix level, [oracle] gnss_channel = "fix"; docs/validation/oracle.md,
    # "Seventh round"): the oracle sees what every method sees (the fix, its reported covariance, the velocity) and
    # is told the world's error structure at fix level, z_i = p_i + fix_common_sigma_m c + l_i + n: c a unit 2-D
    # Gauss-Markov state shared by every receiver (common_tau_s), l_i + n the receiver's local error in metres of
    # covariance C_i: the report's position block times fix_local_scale^2 where the reported per-axis std exceeds
    # fix_local_above_m, else times fix_local_below_scale^2, less fix_local_common_m2 I, floored at
    # fix_local_floor_m^2 per axis (:meth:`fix_local_cov`); l_i (1 - fix_noise_share) C_i stationary, Gauss-Markov
    # over the distance travelled (local_corr_length_m) and time (tau_s), n white fix_noise_share C_i. The
    # velocity: the reported block times fix_velocity_scale^2 above the same threshold. NLOS: the innovation gate.
    fix_common_sigma_m: float = 1.0
    fix_local_above_m: float = math.inf
    fix_local_scale: float = 1.0
    fix_local_below_scale: float = 1.0
    fix_local_common_m2: float = 0.0
    fix_local_floor_m: float = 0.3
    fix_velocity_scale: float = 1.0

    def __post_init__(self):
        if self.gnss not in GNSS_WORLDS:
            raise ValueError(f"gnss must be one of {GNSS_WORLDS}, got {self.gnss!r}")
        for key in ("common_share", "field_share"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise ValueError(f"{key} must be in [0, 1]")
        if not 0.0 < self.fix_noise_share <= 1.0:
            raise ValueError("fix_noise_share must be in (0, 1]")
        if not 0.0 <= self.gate_level < 1.0:
            raise ValueError("gate_level must be in [0, 1) (0: no gate)")

    @property
    def correlated(self) -> bool:
        return self.gnss != "white"

    @property
    def imu(self) -> bool:
        return self.accel_turn_on_sigma is not None

    @property
    def bias_offset(self) -> int:
        """Index of the accelerometer bias in a vehicle block."""
        return 6 if self.correlated else 4

    @property
    def heading_offset(self) -> int:
        """Index of the heading (then the gyroscope bias) in a vehicle block."""
        return self.bias_offset + (2 if self.imu else 0)

    @property
    def heading_dim(self) -> int:
        """2 (heading, gyroscope bias) with ``heading_state`` and a gyroscope model, else 0."""
        return 2 if (self.heading_state and self.imu and self.gyro_turn_on_sigma is not None) else 0

    @property
    def vehicle_dim(self) -> int:
        return self.heading_offset + self.heading_dim

    @property
    def common_dim(self) -> int:
        if self.gnss == "fix":
            return 2
        return 2 if self.correlated and self.common_share > 0 else 0

    @property
    def field_dim(self) -> int:
        """4 M coefficient states of the exact field (``field_omega`` given), else 0."""
        if self.gnss != "field" or self.field_share == 0 or self.field_omega is None:
            return 0
        return 4 * len(self.field_omega)

    @property
    def satellite_dim(self) -> int:
        """"satellites": 2 S + 1 unit Gauss-Markov states, clock/orbit per satellite, vertical ionosphere per
        satellite, the zenith troposphere (one for the net); else 0."""
        return 2 * self.sv_count + 1 if self.gnss == "satellites" else 0

    @property
    def tail_dim(self) -> int:
        """The shared states after the features: common (``common_dim``), field coefficients, satellites."""
        return self.common_dim + self.field_dim + self.satellite_dim

    def tail_coefficients(self, dt: float) -> np.ndarray:
        """Gauss-Markov coefficient of every shared state for a step of ``dt`` (common, field, satellites)."""
        a_c = math.exp(-dt / self.common_tau_s) if self.common_tau_s > 0 else 0.0
        a_f = math.exp(-dt / self.field_tau_s) if self.field_tau_s > 0 else 0.0
        a_s = math.exp(-dt / self.sv_tau_s) if self.sv_tau_s > 0 else 0.0
        return np.concatenate([np.full(self.common_dim, a_c), np.full(self.field_dim, a_f),
                               np.full(self.satellite_dim, a_s)])

    def satellite_columns(self, elevation: np.ndarray) -> np.ndarray:
        """(S, 2 S + 1): d (common pseudorange error of each satellite) / d (satellite states) at the elevations
        (rad): sv_clock_orbit, iono_vertical F(el), tropo_zenith m(el) (couplers/sensing/gnss_satellites.py)."""
        el = np.asarray(elevation, dtype=float)
        s = el.size
        semi = el / math.pi
        f_iono = 1.0 + 16.0 * (0.53 - semi) ** 3  # Klobuchar obliquity (IS-GPS-200, 20.3.3.5.2.5)
        m_tropo = 1.001 / np.sqrt(0.002001 + np.sin(el) ** 2)  # RTCA DO-229, A.4.2.4
        out = np.zeros((s, 2 * s + 1))
        out[np.arange(s), np.arange(s)] = self.sv_clock_orbit_m
        out[np.arange(s), s + np.arange(s)] = self.iono_vertical_m * f_iono
        out[:, 2 * s] = self.tropo_zenith_m * m_tropo
        return out

    def own_variances(self, elevation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(white (S,), multipath (S,)) variances of a receiver's own pseudorange error per satellite: code noise
        a^2 + b^2 / sin el, multipath (m / sin el)^2 (sin el floored at 0.05 as the world's)."""
        s = np.maximum(np.sin(np.asarray(elevation, dtype=float)), 0.05)
        mp = (self.multipath_m / s) ** 2
        white = self.code_noise_a_m ** 2 + self.code_noise_b_m ** 2 / s
        if not self.multipath_state:
            white = white + mp
        return white, mp

    def fix_local_cov(self, gnss_r: np.ndarray) -> np.ndarray:
        """(N, 2, 2) covariance C_i of each receiver's local error ("fix"): the reported position block, times
        fix_local_scale^2 where its per-axis std exceeds fix_local_above_m (else fix_local_below_scale^2), less
        fix_local_common_m2 I, its eigenvalues floored at fix_local_floor_m^2."""
        r = np.asarray(gnss_r, dtype=float)[:, :2, :2]
        std = np.sqrt(0.5 * (r[:, 0, 0] + r[:, 1, 1]))
        k = np.where(std > self.fix_local_above_m, self.fix_local_scale ** 2, self.fix_local_below_scale ** 2)
        cov = k[:, None, None] * r - self.fix_local_common_m2 * np.eye(2)
        lam, vec = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, 1, 2)))
        lam = np.maximum(lam, self.fix_local_floor_m ** 2)
        return np.einsum("nij,nj,nkj->nik", vec, lam, vec)

    def fix_velocity_cov(self, gnss_r: np.ndarray) -> np.ndarray:
        """(N, 2, 2) the reported velocity block, times fix_velocity_scale^2 where the reported per-axis position
        std exceeds fix_local_above_m ("fix")."""
        r = np.asarray(gnss_r, dtype=float)
        std = np.sqrt(0.5 * (r[:, 0, 0] + r[:, 1, 1]))
        k = np.where(std > self.fix_local_above_m, self.fix_velocity_scale ** 2, 1.0)
        return k[:, None, None] * r[:, 2:, 2:]

    def field_basis(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2, field_dim): d F(p_i) / d coefficients per axis, at the points ``xy`` (layout of the world's
        ``coef`` (cos/sin, feature, axis) flattened)."""
        om = np.asarray(self.field_omega, dtype=float).reshape(-1, 2)
        m = om.shape[0]
        phase = np.asarray(xy, dtype=float).reshape(-1, 2) @ om.T  # (N, M)
        basis = np.stack([np.cos(phase), np.sin(phase)], axis=1) / math.sqrt(m)  # (N, 2 cos/sin, M)
        out = np.zeros((phase.shape[0], 2, 2, m, 2))
        out[:, 0, :, :, 0] = basis
        out[:, 1, :, :, 1] = basis
        return out.reshape(phase.shape[0], 2, 4 * m)

    @property
    def gate_threshold(self) -> float:
        return math.inf if (not self.nlos or self.gate_level == 0) else -2.0 * math.log1p(-self.gate_level)

    def local_coefficient(self, dist: np.ndarray, dt: float) -> np.ndarray:
        """a_l per vehicle for a step of ``dt`` in which it moved ``dist`` (module docstring)."""
        d = np.asarray(dist, dtype=float)
        own = np.exp(-d / self.local_corr_length_m - (dt / self.tau_s if self.tau_s > 0 else np.inf))
        if self.gnss != "field" or self.field_share == 0 or self.field_dim:
            return own
        fld = np.exp(-d / self.field_corr_length_m - (dt / self.field_tau_s if self.field_tau_s > 0 else np.inf))
        return self.field_share * fld + (1.0 - self.field_share) * own
