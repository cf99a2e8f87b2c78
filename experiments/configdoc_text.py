"""The text of docs/configuration.md that the schema cannot give: what each table is for
(:data:`TABLE_DOCS`) and the unit and meaning of each key (:data:`KEY_DOCS`), written here because the
dataclasses (some of them in ``coloc`` and ``couplers``) carry them only as scattered comments.
:mod:`experiments.configdoc` checks them against the loader's schema and renders the page.
"""

from __future__ import annotations

from coloc.methods.registry import METHODS, runnable_methods
from experiments.config import SCENARIO_KINDS

INFRA_METHODS = tuple(m for m in runnable_methods() if METHODS[m].infrastructure)

#: Unit of a dimensionless number.
NO_UNIT = "1"

#: What each table is for (one paragraph under its heading).
TABLE_DOCS: dict[str, str] = {
    "oracle": "Optional: the settings of the `joint_oracle` reference (docs/validation/oracle.md). Absent: as "
                    "`gnss_channel = \"receiver\"`.",
    "analysis": "Optional: how a run is scored. summary.json, the reports' CDFs and the sweeps' tables "
                "leave out the estimates with t < `scenario.begin_s` + `warmup_s` (the net fills from empty); "
                "estimates.parquet keeps every row, so the statistics can be recomputed. summary.json "
                "states it in its `analysis` block.",
    "run": "What to run: the name, the seed of every random stream, the simulated duration and the "
           "methods. The only required table.",
    "scenario": "Where the frames come from: SUMO traffic on a net folder (`kind = \"sumo\"`) or one of "
                "the controlled scenarios of Brambilla et al. Sec. V (`\"single_road\"`, `\"crossroad\"`), "
                "each configured by the table of the same name. `net_dir`, `control` and `ballistic` are "
                "refused for the controlled scenarios.",
    "single_road": "Brambilla et al. Sec. V-A: two connected vehicles in one lane passing two static "
                   "features on the sidewalk (Fig. 7). Only with `scenario.kind = \"single_road\"`. The "
                   "scenario senses with its own parameters: `[sensors]`, `[motion] sigma_along / "
                   "sigma_cross` and `scenario.step_s` are taken from this table (a different value given "
                   "there is refused).",
    "crossroad": "Brambilla et al. Sec. V-B: 12 vehicles in four clusters of three crossing a junction, "
                 "features on the sidewalks within 150 m (Figs. 8-11). Only with `scenario.kind = "
                 "\"crossroad\"`. As for `[single_road]`, sensing, driving noise and step come from this "
                 "table; `icp.feature_sigma_par` defaults to `feature_speed_mps / 100` when the features move.",
    "sensors": "On-board sensing of a SUMO run (GNSS comes from the net folder's `zones.geojson`, per "
               "zone). For the controlled scenarios it is derived from their table.",
    "motion": "Driving noise of the estimators' motion model (1), rotated to the heading.",
    "icp": "Gaussian ICP (BPA-L with average consensus), shared by `icp_known_da`, `icp_da_lc` and the "
           "particle methods (feature tracks and their messages).",
    "lc": "ICP-DA-LC: BP data association (13)-(17), MAP pairing (30)-(31), feature tracks without a map. "
          "Also used by `icp_da_pf` for association and tracks.",
    "pf": "ICP-DA-PF (`icp_da_pf`, `icp_known_da_pf`): particle counts, the pair-sum kernel and the "
          "departures from the paper's literal recursion. Its generators are seeded with `run.seed`.",
    "report": "The per-run HTML report.",
    "perception": "Realistic perception (optional table, SUMO only; `couplers/sensing/perception.py`): sensors with "
                  "a field of view and range relative to the heading, detection probability falling with "
                  "distance, range-dependent noise, Poisson clutter over the field of view, occlusion by "
                  "every SUMO vehicle and by the net folder's buildings. Absent: the paper's idealised V2F "
                  "sensing (every feature within `sensors.v2f_range_m`), exactly as before. Each effect "
                  "draws from its own seeded stream.",
    "features": "Moving features from SUMO (optional table, SUMO only; `couplers/sensing/pedestrians.py`): with "
                "`pedestrians = true` every SUMO person of the net folder's persons file (`[files] persons`, e.g. "
                "`sumo_nets/arterial_ped`) is a feature of model (2), measured by the same V2F path as the "
                "static landmarks, and every V2F row carries a class label (`Frame.v2f_class`: 0 static, 1 "
                "pedestrian). Feature tracks use their class's model (2) noise (`icp.pedestrian_sigma_par`) "
                "and a row is only associated with tracks of its class. Methods: `gnss`, `icp_known_da`, "
                "`icp_da_lc` (others are refused). Absent or false: no classes, exactly as before.",
    "perception.sensors": "One sensor of `[perception]` (repeat the table for each sensor). Defaults and "
                          "their sources (datasheet, peer simulator): `couplers/sensing/perception.py`.",
    "estimator_sensors": "The estimators' own sensor model (optional table, SUMO only; "
                         "`experiments/estimator_sensors.py`): datasheet values the estimators use instead of "
                         "the world's `[perception]` sensors: the detection model of `lc.sensor_fov`, "
                         "`lc.clutter_intensity` (when not given: the sensors' false alarms per scan over the "
                         "union of their fields of view) and `lc.sensing_range_m` (when not given: their largest "
                         "reach). Absent: the estimators take these from `[perception]`, exactly as before.",
    "estimator_sensors.sensors": "One sensor of `[estimator_sensors]`, with the keys of a "
                                 "`[[perception.sensors]]` table (the datasheet's values; the noise keys are "
                                 "recorded, the estimators read each row's covariance from the frame).",
    "gnss_error": "Realistic GNSS error (optional table, SUMO only; `couplers/sensing/gnss_error.py`): first-order "
                  "Gauss-Markov position error with the zone's sigma and correlation time `tau_s`, plus NLOS "
                  "bias episodes (`model = \"per_vehicle\"`), or errors nearby vehicles share (`model = \"field\"`); "
                  "with these two the estimators keep the nominal zone covariance a receiver reports. "
                  "`model = \"satellites\"` (`couplers/sensing/gnss_satellites.py`): a receiver at pseudorange "
                  "level, GPS + Galileo seen past the net folder's buildings (every building needs its `height`), "
                  "a weighted least-squares fix with fault exclusion, and the covariance that receiver reports is "
                  "the frame's GNSS covariance.",
    "inertial": "Realistic inertial input (optional table, SUMO only; `couplers/sensing/inertial.py`): a body-frame IMU "
                "per vehicle, longitudinal and lateral acceleration and yaw rate over the step, each with white "
                "noise, a turn-on bias drawn when the vehicle enters and a first-order Gauss-Markov drift. The "
                "estimators rotate the body-frame acceleration into the net frame by their own estimated heading "
                "(`coloc/core/inertial.py`): the velocity estimate's direction, dead-reckoned by the measured yaw "
                "rate below `motion.heading_min_speed`. Absent: the net-frame input with a perfect heading plus "
                "`sensors.accel_sigma` noise, exactly as before. Not with `[infra]`. Defaults: the IMU defaults "
                "(ADIS16448) of the RotorS / PX4 SITL Gazebo IMU plugin; each effect draws from its own seeded "
                "stream.",
    "v2x": "Realistic V2X (optional table, SUMO only; `couplers/sensing/v2x.py`): a share of equipped vehicles "
           "(the others are not estimated, send nothing and are not in the V2V graph, but stay in the traffic "
           "statistics and still occlude sight lines), a packet delivery ratio by link distance with a separate "
           "curve for links through a building of the net folder's `buildings.geojson` (no buildings: every "
           "link is line of sight), independent losses per message and round in each direction, and a budget "
           "of broadcast rounds per step. The V2V graph `neighbors` keeps its meaning (within "
           "`sensors.v2v_range_m`); the channel is a layer on top, carried to the estimators in the frame "
           "(`Frame.v2x`, docs/architecture.md). Default delivery curves derived from 3GPP TR 37.885 V15.3.0 "
           "(2019) Table 6.2.1-1 (V2V urban pathloss, LOS and NLOS, with their 3 / 4 dB shadowing) with a "
           "23 dBm transmitter, 3 dBi antennas, the -82 dBm sensitivity of IEEE 802.11-2016 Table 17-18 (10 "
           "MHz, 6 Mb/s) and Rayleigh fading per packet; no interference or congestion (derivation: "
           "`couplers/sensing/v2x.py`). Absent: every vehicle connected over perfect links, exactly as before. Not "
           "for the controlled scenarios, nor together with `[infra]`.",
    "gnss_model": "The integrator's GNSS receiver error model for `gnss` (optional table; "
                  "`coloc/methods/gnss_bias.py`): a first-order Gauss-Markov bias state per vehicle, which "
                  "takes `bias_share` of the receiver's reported position variance (`frame.gnss_R`, per step and "
                  "vehicle), and a chi-square gate that excludes the position of a fix whose position innovation "
                  "is improbable. Never read from `[gnss_error]` (the world's table): its values are what an "
                  "integrator would assume. Reports and NEES use the 4-D kinematic marginal. The infrastructure "
                  "methods `fg_topology_new` (the bias as a Gauss-Markov chain of factors, `coloc/methods/fg_bias.py`) "
                  "and `sme` (a bias block per vehicle in the joint EKF) take it too, and their internal tracker is "
                  "then this one. Absent: the white tracker of the paper, exactly as before.",
    "fusion": "Consistent cooperative fusion (optional table; `coloc/inference/split_ci.py`, "
              "`coloc/methods/coop_fusion.py`): `icp_known_da` and `icp_da_lc` exchange only their own-sensor "
              "messages and fuse the feature evidence by split covariance intersection (the step's V2F noise "
              "independent, everything else of unknown correlation), so their covariances bound their errors; "
              "ICP-DA-LC's association, births and existence then gate on that covariance. With `bias_state` "
              "they also carry `[gnss_model]`'s receiver model. `icp_da_pf` (and `icp_known_da_pf`) localize "
              "their vehicles the same way, on 6-D split filters, and keep their particles for the association "
              "and the feature tracks (`coloc/methods/pf_fusion.py`); `rsu_bp` does so at its RSUs. `sme` "
              "takes a vehicle that re-enters an RSU's joint state by covariance intersection "
              "(`coloc/methods/infra.py`). Absent: the paper's Gaussian BPA-L and particle BPA-L, and the "
              "paper's `rsu_bp` and `sme`, exactly as before.",
    "infra": "Infrastructure mode (optional table, SUMO only): road-side units at junctions of the net, "
             "their radar and the settings of the infrastructure methods "
             f"({', '.join(f'`{m}`' for m in INFRA_METHODS)}), which need this table. A config without it "
             "runs exactly as before; a sweep can set its keys only when the base config has the table.",
}

# On-board sensing: the keys of [sensors], which the controlled scenarios also carry.
_SENSING: dict[str, tuple[str, str]] = {
    "accel_sigma": ("m/s^2", "White noise per axis on the reported inertial input a_{t-1}."),
    "v2f_range_m": ("m", "V2F sensing range Rs (`inf`: always in range)."),
    "v2f_sigma_p": ("m", "V2F relative position noise, model (4)."),
    "v2f_sigma_v": ("m/s", "V2F relative velocity noise, model (4)."),
    "v2v_range_m": ("m", "V2V range Rc (`inf`: always connected)."),
    "prior_sigma_p": ("m", "Fast-start prior around the true state at a vehicle's first frame, position "
                           "(Sec. VI-A; Sec. V states no initialisation). Controlled scenarios: only with "
                           "`start = \"fast_start\"`."),
    "prior_sigma_v": ("m/s", "Fast-start prior around the true state, velocity."),
}

# Keys shared by [single_road] and [crossroad] (couplers.scenarios._Common).
_SCENARIO_COMMON: dict[str, tuple[str, str]] = {
    **_SENSING,
    "accel_sigma": ("m/s^2", _SENSING["accel_sigma"][1] + " The paper: 0."),
    "dt": ("s", "Sampling interval Ts of the scenario (also the estimators' step)."),
    "speed_kmh": ("km/h", "Reference speed of the vehicles."),
    "sigma_along": ("m/s^2", "Along-track driving noise of model (1), truth and estimators."),
    "sigma_cross": ("m/s^2", "Cross-track driving noise of model (1), truth and estimators."),
    "gnss_sigma_p": ("m", "GNSS position noise sp per axis, model (3)."),
    "gnss_sigma_v": ("m/s", "GNSS velocity noise sv per axis, model (3)."),
    "start": ("", "The fix a vehicle starts from: `\"fast_start\"` (ours; the Sec. VI-A prior, prior_sigma_p / "
                  "prior_sigma_v around the truth) or `\"gnss_fix\"` (the paper presets: a first receiver fix "
                  "with the scenario's GNSS sigmas, Sec. V stating no initialisation)."),
    "speed_gain": ("1/s", "Along-track input kv (v_ref - v) of the truth: speed gain kv."),
    "gap_gain": ("1/s^2", "Followers' input: gap gain kg on (gap - headway)."),
    "rel_speed_gain": ("1/s", "Followers' input: relative-speed gain kr on (v_lead - v)."),
}

#: (unit, meaning) of every key the loader accepts, per table. Unit NO_UNIT for a
#: dimensionless number, "" for strings, booleans and lists of names.
KEY_DOCS: dict[str, dict[str, tuple[str, str]]] = {
    "oracle": {
        "gnss_channel": ("", "What the oracle sees of the receivers under `[gnss_error] model = \"satellites\"`: "
                             "`receiver` (each receiver's WLS gain over the satellites, the satellites it used and "
                             "which came by reflection; the satellites' shared errors as states) or `fix` (only the "
                             "fixes, their reported covariance and velocity, as every other method; told the "
                             "world's fix-level error structure measured on tuning seeds: one common-mode error "
                             "shared by every receiver, a local error per vehicle sized by the calibrated report; "
                             "the frames are then those of a run without the oracle). `fix` in the satellite "
                             "world only."),
    },
    "analysis": {
        "warmup_s": ("s", "Scoring warm-up after the begin (0: score everything). The realistic arterial "
                          "presets use 600 s: the TLR net holds about 150 vehicles from minute 6 on "
                          "(`tools/net_fill.py`)."),
        "warmup_start": ("", "What runs during the warm-up (SUMO scenarios): `sensed` (sensing and estimation from "
                             "the begin; the warm-up's rows are written, not scored) or `traffic` (SUMO alone "
                             "drives the warm-up, about 1.4 s of CPU for 600 s of the TLR arterial; sensing, its "
                             "random streams and the estimators start at begin + warmup_s, every vehicle on the "
                             "road entering then with its prior). Why not SUMO's saved state: `docs/protocol.md`."),
    },
    "run": {
        "name": ("", "Name of the run (progress bar, the `run` column of estimates.parquet)."),
        "seed": (NO_UNIT, "Seed of every random stream (SUMO, sensors, particle generators); same config and "
                          "seed give a byte-identical estimates.parquet. `coloc run --seed` overrides it."),
        "duration_s": ("s", "Simulated duration; a controlled scenario also ends by itself. "
                            "`coloc run --duration` overrides it."),
        "methods": ("", "Estimators to run, one or more of: "
                        + ", ".join(f"`{m}`" for m in runnable_methods()) + ". `coloc run --methods` overrides it."),
    },
    "scenario": {
        "kind": ("", "Frame source, one of: " + ", ".join(f"`{k}`" for k in SCENARIO_KINDS) + "."),
        "net_dir": ("", "Net folder (relative to the config file that writes it, also a parent of `extends`); "
                        "required for `kind = \"sumo\"`."),
        "control": ("", "Traffic control of a SUMO run: `\"tlr\"` (traffic lights) or `\"vsr\"` (every signal "
                        "off, gap acceptance), as the net folder's `scenario.toml` defines them."),
        "step_s": ("s", "Simulation and estimation step Ts (the arterial: 0.75 s). Derived from the scenario "
                        "table for the controlled scenarios."),
        "ballistic": ("", "SUMO's ballistic position update (`--step-method.ballistic`), so SUMO's kinematics "
                          "match model (1) with piecewise-constant acceleration."),
        "begin_s": ("s", "Begin of a SUMO run on the scenario's own clock (seconds since midnight, e.g. 25200 = "
                         "07:00; SUMO's `--begin`): the run simulates [begin_s, begin_s + run.duration_s], SUMO "
                         "drops vehicles departing before it, and estimates' `t` and the reports' time axes are "
                         "on that clock. >= 0; a begin after the demand's last departure is refused. Not set: the "
                         "net folder's `[sumo] begin` (0 without one; `coloc net import --sumocfg` writes the "
                         "scenario's). The folder's `[sumo] step_length` and `end` likewise give `step_s` and "
                         "`run.duration_s` (= end - begin) when they are not set."),
        "start": ("", "SUMO only: the prior of an entering (or teleported) vehicle. `\"fast_start\"`: N(truth, "
                      "`sensors.prior_sigma_p/v`), the paper's; `\"gnss_fix\"`: its receiver's fix of that step and "
                      "the covariance the receiver reports (nothing of its truth)."),
        "reference_point": ("", "SUMO only: the point of a vehicle the world reports (frames, truth, GNSS error, "
                                "sensor mounts, V2V ranges). `\"front_bumper\"`: SUMO's position, the centre of "
                                "the front bumper (the paper configs'); `\"centre\"`: half the vehicle's SUMO "
                                "length behind it along its angle, whose velocity is the reported speed x heading "
                                "(a bumper slides sideways at about length / 2 x yaw rate in a turn; "
                                "docs/validation/consistency.md \"Kinematics of the world\"). "
                                "`perception.sensors.mount_x_m` is measured from this point."),
    },
    "single_road": {
        **_SCENARIO_COMMON,
        "n_vehicles": (NO_UNIT, "Vehicles in the lane."),
        "headway_m": ("m", "Front-to-front spacing of the vehicles at the start."),
        "feature_spacing_m": ("m", "df, spacing of the two features (the paper: 0.5, 3 and 6 m)."),
        "road_length_m": ("m", "Road length (not in the paper; our choice)."),
        "sidewalk_offset_m": ("m", "Lateral distance of the features from the lane centre (our choice)."),
        "duration_s": ("s", "Scenario duration; not set: ceil(road_length_m / speed)."),
    },
    "crossroad": {
        **_SCENARIO_COMMON,
        "vehicles_per_cluster": (NO_UNIT, "Vehicles per cluster; one cluster per arm (four)."),
        "arm_length_m": ("m", "Distance from the junction centre to the edge of the area on each arm."),
        "cluster_headway_m": ("m", "Spacing inside a cluster (not in the paper; our choice)."),
        "lane_offset_m": ("m", "Lane centre from the road axis (half a 3.5 m lane; our choice)."),
        "n_features": (NO_UNIT, "Nf, number of features (the paper sweeps 3, 10, 20, 60)."),
        "feature_disc_radius_m": ("m", "Features' initial locations lie within this radius of the centre."),
        "feature_layout": ("", "`\"sidewalks\"` (uniform on the sidewalks inside the disc, the paper) or "
                               "`\"disc\"` (uniform over the whole disc)."),
        "sidewalk_offset_m": ("m", "Sidewalk line from the road axis (our choice: lane centre + 3 m)."),
        "feature_speed_mps": ("m/s", "vf, initial feature speed along the sidewalk (the paper: 0, 1, 2, 5)."),
        "area_ring_m": ("m", "Width of the distance rings around the centre used as analysis areas."),
        "max_duration_s": ("s", "Scenario duration cap; not set: twice the nominal crossing time."),
        "centre": ("m", "Junction centre [x, y]."),
    },
    "sensors": {
        **_SENSING,
        "perception": ("", "Not a key of the file (refused there): carries the `[perception]` table to the "
                           "coupler."),
        "gnss_error": ("", "Not a key of the file (refused there): carries the `[gnss_error]` table to the "
                           "coupler."),
        "v2x": ("", "Not a key of the file (refused there): carries the `[v2x]` table to the coupler."),
        "inertial": ("", "Not a key of the file (refused there): carries the `[inertial]` table to the "
                         "coupler."),
        "features": ("", "Not a key of the file (refused there): carries the `[features]` table to the "
                         "coupler."),
    },
    "estimator_sensors": {
        "sensors": ("", "One `[[estimator_sensors.sensors]]` table per sensor (required)."),
    },
    "inertial": {
        "accel_noise_density": ("m/s^2/sqrt(Hz)", "Accelerometer white-noise density per axis (longitudinal, "
                                                  "lateral); the step's mean has std density / sqrt(Ts). "
                                                  "Default 0.004: RotorS / PX4 SITL IMU plugin (ADIS16448)."),
        "accel_bias_sigma": ("m/s^2", "Stationary std of the accelerometer bias drift (first-order Gauss-Markov) "
                                      "per axis. Default 0.0735 = random walk 0.006 m/s^3/sqrt(Hz) x sqrt(tau / 2) "
                                      "of RotorS."),
        "accel_bias_tau_s": ("s", "Correlation time of the accelerometer bias drift. Default 300 s: RotorS."),
        "accel_turn_on_sigma": ("m/s^2", "Std of the accelerometer turn-on bias per axis, drawn when a vehicle "
                                         "enters and then constant. Default 0.196 (20 mg): RotorS."),
        "gyro_noise_density": ("deg/s/sqrt(Hz)", "Yaw-rate white-noise density. Default 0.01944 (= 70 deg/h/sqrt(Hz)): "
                                                 "RotorS."),
        "gyro_bias_sigma": ("deg/s", "Stationary std of the yaw-rate bias drift (first-order Gauss-Markov). "
                                     "Default 0.0497 = random walk 2 x 4 / 3600 deg/s^2/sqrt(Hz) x sqrt(tau / 2) of RotorS."),
        "gyro_bias_tau_s": ("s", "Correlation time of the yaw-rate bias drift. Default 1000 s: RotorS."),
        "gyro_turn_on_sigma": ("deg/s", "Std of the yaw-rate turn-on bias, drawn when a vehicle enters. Default "
                                        "0.5 deg/s: RotorS."),
    },
    "gnss_model": {
        "bias_share": (NO_UNIT, "Share of the reported position variance that is a slowly varying bias, in [0, "
                                "1); the white rest, (1 - share) R_pos, is the fix's noise. The bias's stationary "
                                "covariance is share x R_pos of the zone the vehicle is in (reached with the "
                                "bias's correlation time after a zone change). 0: a white tracker (with the gate). "
                                "Default 0.8 (assumption: code noise of decimetres against metres of slow "
                                "atmospheric, orbit/clock and multipath error)."),
        "bias_tau_s": ("s", "Correlation time of the bias: b_k = a b_{k-1} + w, a = exp(-Ts / tau), Var(w) = "
                            "(1 - a^2) share R_pos. Default 60 s (assumption: single-frequency position errors "
                            "correlate over tens of seconds to minutes)."),
        "innovation_gate": (NO_UNIT, "Level of the chi-square gate (2 degrees of freedom) on the normalized "
                                     "innovation squared of the fix's position: a fix beyond the quantile is "
                                     "excluded: its position is skipped, its velocity still updates (skipping "
                                     "the whole fix let trackers diverge with a biased IMU); a vehicle's first "
                                     "fix is never gated. In [0, 1); 0: no exclusion. Default 0.999 (threshold "
                                     "13.8)."),
        "max_exclusions": (NO_UNIT, "Consecutive excluded fixes of a vehicle after which the next fix is taken "
                                    "whatever its innovation (a lasting discrepancy is more likely the "
                                    "tracker's own drift than a fault; a gate that never reopens diverges). "
                                    "Default 10 (assumption: NLOS episodes last seconds)."),
        "bias_follows_report": ("", "When a vehicle's reported position covariance changes (a zone change), "
                                    "its bias is mapped by the change of the report's Cholesky factor, so the "
                                    "bias variance is share x the new report at once (a position error is the "
                                    "range errors times the geometry: Kaplan and Hegarty 2017, Sec. 7.3). "
                                    "`gnss`, and the cooperative methods under `two_state`. Default false: "
                                    "the bias carries over and its variance relaxes with `bias_tau_s`."),
        "bias_model": ("", "The receiver's error as one bias (`single`: `bias_share`, `bias_tau_s`) or two "
                           "(`two_state`, coloc/methods/gnss_bias2.py): a common-mode bias slow in time "
                           "(atmosphere, orbit, clock) and a local one decorrelating with the distance the "
                           "estimator believes it travelled (multipath); fix z = p + c + l + n. `gnss` and, with "
                           "`[fusion]`, the cooperative methods (coloc/methods/coop_fusion.py: the feature "
                           "evidence in the common-mode frame, c a consider state of the fusion); the "
                           "infrastructure methods keep the single bias. Default `single`."),
        "common_share": (NO_UNIT, "Two-state model: share of the reported position variance that is the "
                                  "common-mode bias, in [0, 1); with `local_share` below 1 together. Default 0.5 "
                                  "(assumption: most of the reported variance is slow, about half of it "
                                  "common-mode; chosen on the tuning seeds 101-103)."),
        "common_tau_s": ("s", "Two-state model: correlation time of the common-mode bias. Default 1800 s "
                              "(residuals of the broadcast atmosphere and orbit/clock models change over tens of "
                              "minutes: Kaplan and Hegarty 2017, Sec. 7.2)."),
        "common_sigma_m": ("m", "Two-state model: the common-mode bias's own size per axis, added to its share "
                                "of the report: stationary covariance common_share R_pos + sigma^2 I. The error "
                                "every range shares with other receivers (clock/orbit, atmosphere) moves the fix "
                                "but not the residuals, so a covariance scaled from the residuals "
                                "(`[gnss_error] reported_covariance = \"residual\"`) does not carry it; this is "
                                "the integrator's size for it, from the receiver's open-sky accuracy. Default 0 "
                                "(the share alone)."),
        "velocity_gate": (NO_UNIT, "Level of a chi-square test (2 dof) on the fix's velocity "
                                   "innovation; a velocity with d^2 above the threshold t is taken with its noise "
                                   "times d^2 / t (robust Kalman filter of G. Chang, J. Geodesy 88, 2014). For "
                                   "range-rate velocities that carry a reflected signal's path rate. Default 0 "
                                   "(no test)."),
        "local_share": (NO_UNIT, "Two-state model: share of the reported position variance that is the local "
                                 "bias, in [0, 1). Default 0.45 (assumption; chosen on the tuning seeds 101-103)."),
        "local_length_m": ("m", "Two-state model: correlation length of the local bias in distance travelled, "
                                "a = exp(-Ts / local_tau_s - |v| Ts / length) with |v| the estimator's own speed "
                                "estimate. Default 30 m (multipath decorrelates over metres to tens of metres of "
                                "travel: Braasch, in Parkinson and Spilker 1996, ch. 14; 30 m chosen over 10 m on "
                                "the tuning seeds 101-103)."),
        "local_tau_s": ("s", "Two-state model: correlation time of the local bias at rest. Default 120 s "
                             "(static multipath changes with the satellites' motion over minutes: ibid.)."),
        "degraded_above_m": ("m", "The receiver's report calibrated against a reference trajectory "
                                  "(`coloc/methods/report_calibration.py`): above this reported per-axis position "
                                  "std the fix's position and velocity covariances are scaled by the two factors "
                                  "below, for every method that takes `[gnss_model]` (not `joint_oracle`). A "
                                  "residual-scaled report under-states reflected signals' errors where few signals "
                                  "remain. Default 0 (the report as it is)."),
        "degraded_position_scale": (NO_UNIT, "Factor on the reported position std above `degraded_above_m`. "
                                             "Default 1."),
        "degraded_velocity_scale": (NO_UNIT, "Factor on the reported velocity std above `degraded_above_m` "
                                             "(it also stands for the time correlation of a reflected signal's "
                                             "path-rate error). Default 1."),
        "velocity_inflation": ("", "What the velocity gate (`velocity_gate`) inflates when a range-rate velocity fails "
                                   "it: `noise` (default) scales the velocity's noise R_vv by d^2 / threshold; "
                                   "`innovation` scales the innovation covariance S_vv by it, so that the inflated "
                                   "statistic is the threshold even where the predicted velocity's covariance "
                                   "dominates S."),
        "gate_on": ("", "The fault exclusion's statistic on the calibrated report (`calibrated`, default) or "
                        "on the report as the receiver gives it (`report`: the receiver's own claim, as RAIM "
                        "reads it); the update takes the calibrated report either way "
                        "(coloc/methods/report_calibration.py). `report` needs `degraded_position_scale` >= 1."),
        "common_update": ("", "Two-state model: the common-mode bias as a state of the filter (`augmented`) or "
                              "a Schmidt consider state (`consider`: its correlations carried, its estimate never "
                              "updated; Simon 2006, Sec. 7.5). Default `consider` (the more consistent on the "
                              "tuning seeds 101-103). Use with `bias_follows_report = true`."),
        "adaptive_window_s": ("s", "Adaptive receiver covariance of `gnss` (coloc/methods/gnss_bias.py; "
                                   "Mohamed and Schwarz, J. Geodesy 1999): the reported position covariance "
                                   "is scaled by m where m passes a 99 % test of consistency (else 1), m the "
                                   "vehicle's exponentially weighted average (this time constant) of its "
                                   "position innovations' NIS per degree of freedom (each capped at the "
                                   "gate's threshold). Not yet in the cooperative methods' own-sensor track. "
                                   "0: off (default)."),
    },
    "fusion": {
        "rule": ("", "How the cooperative methods fuse what they receive: `split_ci` (split covariance "
                     "intersection; weights: fast CI across a vehicle's features, then the minimum determinant "
                     "of the kinematic covariance against its prior), or `bp`: the paper's Gaussian BP "
                     "propagation, as without the table (the other keys unused; a sweep's before arm)."),
        "bias_state": ("", "The cooperative methods take `[gnss_model]`'s receiver model (a Gauss-Markov bias "
                           "state per vehicle and fault exclusion of the fix) when the config has that table; "
                           "false, or no `[gnss_model]`: the white receiver."),
        "common_mode_gnss": ("", "The receivers' errors may be shared between nearby vehicles (atmosphere, "
                                 "orbit and clock): what a vehicle's own fixes put in its belief counts as of "
                                 "unknown correlation with the other vehicles' messages (the dependent part of "
                                 "split CI). False: every receiver's error its own, as the paper's model (3)."),
        "feature_ci": ("", "A feature's evidence to a vehicle is the covariance intersection (equal weights, the "
                           "consensus average) of this step's other observers' own-sensor messages instead of the "
                           "sum of every message the track keeps: the other vehicles' messages may share their "
                           "receivers' errors. False: their sum (independent receivers)."),
        "common_frame_messages": ("", "Two-state receiver model (`[gnss_model] bias_model = \"two_state\"`): a "
                                      "vehicle's own-sensor message to the features (and ICP-DA-LC's tracks) is "
                                      "its own track in the common-mode frame, [p + c, v] with that covariance, "
                                      "the frame the feature evidence is taken in (coloc/methods/coop_fusion.py). "
                                      "False: the position marginal, whose covariance holds the common-mode "
                                      "variance. Default false."),
        "belief_innovation_gate": (NO_UNIT, "The cooperative belief's fault exclusion of the receiver's fix: the "
                                            "chi-square level (2 dof) of its gate on the position innovation, where "
                                            "it differs from `[gnss_model] innovation_gate` (which the own-sensor "
                                            "track and `gnss` keep). -1 (default): `[gnss_model]`'s."),
        "belief_max_exclusions": (NO_UNIT, "The cooperative belief's longest run of excluded fixes before it takes "
                                           "the next one, where it differs from `[gnss_model] max_exclusions`: the "
                                           "belief has the landmarks' evidence, so it can ride out a longer run of "
                                           "reflected fixes than a receiver alone. -1 (default): `[gnss_model]`'s."),
        "map_drift": ("", "With `common_frame_messages` and the two-state model: the part of every track that "
                          "came from vehicles no longer observing it (the folded messages of (12)) drifts as the "
                          "common-mode frame does, by the common-mode bias's driving noise "
                          "common_sigma_m^2 (1 - exp(-2 dt / common_tau_s)) per axis and step (`[gnss_model]`), so "
                          "a map kept over the run follows the frame the vehicles see now (`icp_known_da`, "
                          "`icp_da_lc`; ICP-DA-PF's particle tracks have no folded part). Default false: model "
                          "(2) alone."),
    },
    "features": {
        "pedestrians": ("", "Every SUMO person is a moving feature with class pedestrian (needs a net folder "
                            "with `[files] persons`; refused on the controlled scenarios)."),
    },
    "v2x": {
        "penetration_rate": (NO_UNIT, "Share of SUMO vehicles with a V2X unit, in (0, 1]: a vehicle is "
                                      "equipped iff a keyed hash of its id and `run.seed` falls below it, so "
                                      "for one seed the equipped set of a lower rate is part of that of a "
                                      "higher rate."),
        "pdr_distance_m": ("m", "Link distances of the delivery table, strictly increasing from >= 0; "
                                "delivery is interpolated linearly in between and is 0 beyond the last."),
        "pdr_los": (NO_UNIT, "Packet delivery ratio at each distance of a line-of-sight link, in [0, 1], "
                             "non-increasing."),
        "pdr_nlos": (NO_UNIT, "Packet delivery ratio at each distance of a link whose segment crosses a "
                              "building, in [0, 1], non-increasing."),
        "rounds_per_step": (NO_UNIT, "Broadcast rounds that fit in one step, shared by every iterative "
                                     "exchange of a method: an integer >= 1, or `\"unlimited\"`."),
        "channel": ("", "`\"curves\"`: delivery by link distance from `pdr_los` / `pdr_nlos`; `\"ideal\"`: "
                        "every link within `sensors.v2v_range_m` delivers every round (the penetration and the "
                        "round budget alone)."),
    },
    "perception": {
        "sensors": ("", "One `[[perception.sensors]]` table per sensor, keys below (default: a front radar "
                        "120 deg / 80 m and a 360 deg / 30 m surround sensor; given tables replace both)."),
        "occlusion_vehicles": ("", "Sight lines blocked by the footprint of any other SUMO vehicle (vType "
                                   "length and width), connected or not."),
        "occlusion_buildings": ("", "Sight lines blocked by the net folder's `buildings.geojson` (when it has "
                                    "one). Given true (here or in a config it extends) on a net folder without "
                                    "buildings: refused."),
        "road_users": ("", "Every other SUMO vehicle (equipped or not) and every SUMO person (when the net has "
                           "persons and `[features] pedestrians` is off) in view and not occluded is detected "
                           "with the sensor's P_D and noise, class vehicle (2) or pedestrian (1); the estimators "
                           "drop vehicle-class rows (`couplers/sensing/road_users.py`)."),
        "persistent_clutter_per_km": ("1/km", "False-alarm sources tied to places, per km of each directed road "
                                              "edge, drawn once per run beside its rightmost lane; reported as "
                                              "static objects. 0: none."),
        "persistent_clutter_pd": (NO_UNIT, "Probability that a persistent false-alarm source in view and not "
                                           "occluded is reported in a scan (default 0.9, an assumption)."),
        "class_error": (NO_UNIT, "Probability that the classifier reports one of the other two classes "
                                 "(default 0: a perfect classifier, an idealisation)."),
        "detections": ("", "`\"net_xy\"` (default): each detection is the relative state x_F - x_V in the net "
                           "frame (model (4)); `\"range_bearing\"`: range, bearing and range rate in the sensor's "
                           "frame with the sigma_r_m / sigma_b_deg / sigma_rdot_mps noise, and every estimator "
                           "rotates them with its own heading estimate (`coloc/core/detections.py`)."),
        "lever_arm_range_rate": ("", "With `detections = \"range_bearing\"`: `true`, the range rate is the "
                                     "sensor's own, its mount point moving with the vehicle's velocity plus yaw "
                                     "rate x `mount_x_m` (the true yaw rate from the heading's change over the "
                                     "step), and the estimators add back that term with their own gyroscope's "
                                     "yaw rate (`[inertial]`; without it, none); `false` (default): relative to "
                                     "the vehicle's velocity (`couplers/sensing/sensor_frame.py`)."),
    },
    "perception.sensors": {
        "name": ("", "Name of the sensor (the row's sensor in the detections)."),
        "fov_deg": ("deg", "Opening of the field of view, in (0, 360]."),
        "range_m": ("m", "Range of the sensor."),
        "yaw_deg": ("deg", "Boresight relative to the heading, counter-clockwise."),
        "mount_x_m": ("m", "Mount point along the heading from the vehicle's reference point (negative: "
                           "rearward): the front bumper centre, or the vehicle's centre with `[scenario] "
                           "reference_point = \"centre\"` (a sensor on the bumper of a 4.5 m car: 2.25)."),
        "pd_near": (NO_UNIT, "Detection probability at 0 m."),
        "pd_far": (NO_UNIT, "Detection probability at the range (the fall-off follows Eclipse MOSAIC's "
                            "distance modifier)."),
        "clutter_per_scan": (NO_UNIT, "Mean false detections per scan (Poisson), uniform over the field of "
                                      "view's area."),
        "sigma_p_m": ("m", "Position noise per axis at 0 m."),
        "sigma_growth": (NO_UNIT, "Position noise at the range is sigma_p_m (1 + sigma_growth), linear in "
                                  "between."),
        "sigma_v_mps": ("m/s", "Velocity noise per axis."),
        "sigma_r_m": ("m", "Range noise std with `detections = \"range_bearing\"` (default: Continental ARS "
                           "408-21, near range)."),
        "sigma_b_deg": ("deg", "Bearing noise std with `detections = \"range_bearing\"`."),
        "sigma_rdot_mps": ("m/s", "Range-rate (radial velocity) noise std with `detections = \"range_bearing\"`."),
    },
    "gnss_error": {
        "tau_s": ("s", "Correlation time of the Gauss-Markov position error; 0 = white noise, exactly today's "
                       "draws."),
        "nlos_zones": ("", "Zones with NLOS bias episodes when the net folder has no buildings."),
        "nlos_rate_per_min": ("1/min", "Episode start rate in each of `nlos_zones` (same order)."),
        "nlos_rate_per_density_per_min": ("1/min", "With buildings: start rate per unit of built-up fraction "
                                                   "around the vehicle."),
        "nlos_density_radius_m": ("m", "Radius of the built-up fraction around the vehicle."),
        "nlos_mean_duration_s": ("s", "Mean episode duration (exponential)."),
        "nlos_bias_mean_m": ("m", "Mean bias magnitude of an episode (exponential, uniform direction)."),
        "model": ("", "`\"per_vehicle\"`: each vehicle's error on its own (the keys above); `\"field\"`: errors "
                      "nearby vehicles share: a common part, a spatial field and the receiver's own part, NLOS "
                      "episodes per cell (the keys below; docs/validation/realistic_sensing.md)."),
        "common_share": (NO_UNIT, "field: share in [0, 1] of each receiver's error variance common to every vehicle "
                             "(atmosphere, orbit, clock)."),
        "common_tau_s": ("s", "field: correlation time of the common part; 0 = white."),
        "field_share": (NO_UNIT, "field: share in [0, 1] of the non-common variance in the spatial field that nearby "
                            "receivers share; the rest is the receiver's own part."),
        "field_corr_length_m": ("m", "field: correlation length of the spatial field (exponential covariance)."),
        "field_tau_s": ("s", "field: correlation time of the spatial field at a fixed place; 0 = white."),
        "field_features": (NO_UNIT, "field: random Fourier features of the spatial field (1 to 4096)."),
        "local_corr_length_m": ("m", "field: distance travelled over which the receiver's own part decorrelates "
                                     "(standing still it keeps it, up to `tau_s`, its time floor)."),
        "nlos_cell_m": ("m", "field: side of the square cells NLOS episodes belong to; every vehicle in a cell "
                             "shares its episode."),
        "elevation_mask_deg": ("deg", "satellites: the receiver uses satellites at or above this elevation, in "
                                      "[0, 90)."),
        "antenna_height_m": ("m", "satellites: antenna height above the road, the start of each sight line."),
        "nlos": ("", "satellites: a satellite whose sight line a building blocks is `\"block\"`: not received, or "
                     "`\"delay\"`: received by reflection with the extra path 2 d cos(el), d the distance to the "
                     "blocking facade, or `\"reflect\"`: received off the nearest facade that gives a clear "
                     "single-bounce specular path, extra path 2 d cos(el) cos(dphi) (d that facade's distance, "
                     "dphi between the satellite's azimuth and the facade's normal), not received when none does."),
        "constellation_time_s": ("s", "satellites: the run's t = 0 after the constellation's epoch (moves the "
                                      "geometry)."),
        "sv_clock_orbit_m": ("m", "satellites: broadcast clock and orbit error per satellite (Gauss-Markov, shared "
                                  "by every receiver)."),
        "iono_vertical_m": ("m", "satellites: vertical ionospheric delay left after the broadcast model, per "
                                 "satellite, times the Klobuchar obliquity factor."),
        "tropo_zenith_m": ("m", "satellites: zenith tropospheric delay left after the receiver's model (one for "
                                "the net), times the RTCA DO-229 mapping."),
        "sv_tau_s": ("s", "satellites: correlation time of the clock/orbit, ionosphere and troposphere errors; "
                          "0 = white."),
        "code_noise_a_m": ("m", "satellites: receiver code noise, white, sigma^2 = a^2 + b^2 / sin(el) (RTKLIB's "
                                "elevation model)."),
        "code_noise_b_m": ("m", "satellites: the b of `code_noise_a_m`."),
        "multipath_m": ("m", "satellites: code multipath at zenith, growing as 1 / sin(el)."),
        "multipath_corr_length_m": ("m", "satellites: distance travelled over which a receiver's multipath "
                                         "decorrelates (a standing vehicle keeps it)."),
        "rx_ure_m": ("m", "satellites, the receiver's own budget (weights and reported covariance, RTKLIB "
                          "pntpos form): broadcast range error."),
        "rx_iono_m": ("m", "satellites, receiver budget: ionosphere at zenith, times the obliquity factor."),
        "rx_tropo_m": ("m", "satellites, receiver budget: troposphere, over sin(el) + 0.1."),
        "rx_code_a_m": ("m", "satellites, receiver budget: code noise a (as `code_noise_a_m`)."),
        "rx_code_b_m": ("m", "satellites, receiver budget: code noise b."),
        "raim_pfa": (NO_UNIT, "satellites: false-alarm probability of the receiver's chi-square residual test; "
                              "a failed test excludes the worst satellite and tries again; 0 = no test."),
        "velocity": ("", "satellites: the receiver's velocity is `\"zone\"`: the zone's white Doppler error "
                         "(as the other models), or `\"doppler\"`: the range-rate least-squares solution over the "
                         "satellites of its fix, with the covariance the receiver reports."),
        "doppler_noise_mps": ("m/s", "satellites, doppler: range-rate noise, white, sigma^2 = s^2 (1 + 1 / sin(el))."),
        "rx_doppler_mps": ("m/s", "satellites, doppler, receiver budget: the s of `doppler_noise_mps` the receiver "
                                  "weights with and reports."),
        "reported_covariance": ("", "satellites: the covariance the receiver reports (fix and Doppler velocity) is "
                                    "`\"dop\"`: its budget through the geometry, (H^T W H)^-1, or `\"residual\"`: "
                                    "that times the fit's a-posteriori variance factor r^T W r / (m - 4) when above "
                                    "1 (m > 4 satellites)."),
        "draws": ("", "satellites: the receiver noise, multipath and Doppler normals are drawn `\"all\"`: for every "
                      "satellite of the constellation each step (the streams do not depend on the sky), or "
                      "`\"visible\"`: only for those above the elevation mask (fewer draws, the same distributions; "
                      "another sequence of values, so other frames than `\"all\"`). A satellite's multipath "
                      "process starts afresh when it rises."),
        "oracle_channel": ("", "satellites: the frames also carry each receiver's WLS gains over the satellites, its "
                               "satellites and which came by reflection (what `joint_oracle` is told; no other "
                               "estimator reads it). Set by the runner for a run whose methods include "
                               "`joint_oracle`; nothing else changes."),
    },
    "motion": {
        "sigma_along": ("m/s^2", "Along-track driving noise s_along of model (1)."),
        "sigma_cross": ("m/s^2", "Cross-track driving noise s_cross of model (1) (the arterial configs: 0.1 "
                                 "instead of the paper's 0.001, see the Brambilla validation page)."),
        "heading_min_speed": ("m/s", "Below this estimated speed the heading is not trusted and the driving "
                                     "noise is isotropic with sigma_along on both axes."),
        "imu_heading": ("", "With `[inertial]`: the heading an estimator rotates the body-frame IMU input with "
                            "while its vehicle is below `heading_min_speed`. \"dead_reckoned\": the kept heading "
                            "plus the gyroscope's yaw rate; \"held\": the kept heading unchanged (a gyroscope's "
                            "bias is not integrated over a stop), as the sensor-frame detections' heading is."),
    },
    "icp": {
        "consensus_iterations": (NO_UNIT, "Average-consensus iterations per feature (BPA-L)."),
        "bpa_max_iterations": (NO_UNIT, "Upper limit of BPA-L iterations (19)-(22) per step."),
        "stop_pos_m": ("m", "BPA-L stops when no position changes by more than this (Sec. V-A: 10 cm)."),
        "stop_vel_mps": ("m/s", "... and no velocity by more than this (Sec. V-A: 0.1 m/s)."),
        "feature_sigma_par": ("m/s", "Velocity random walk per step of a feature, model (2) (moving "
                                     "features: vf / 100)."),
        "pedestrian_sigma_par": ("m/s", "Velocity random walk per step of a pedestrian track, model (2) "
                                        "(sv_perp = sv_par / 2). Default 0.05, measured on `arterial_ped`: the "
                                        "Sec. V-B rule vf / 100 = 0.013 is too tight for SUMO's walkers "
                                        "(docs/validation/realistic_sensing.md, \"SUMO pedestrians\")."),
        "feature_drop_after_s": ("s", "A track no vehicle observed for this long is dropped (the paper's "
                                      "reset to a uniform belief)."),
        "feature_velocity_prior_sigma": ("m/s", "Velocity prior N(0, s^2 I) of a newborn track; 0 = uniform "
                                                "(the paper's reset)."),
        "message_memory_s": ("s", "How long a track keeps the latest message of a vehicle apart."),
        "feature_message": ("", "What a track stores of each vehicle: `\"own\"` (the own-sensor belief, "
                                "default) or `\"bpa\"` (BPA-L's final message (19))."),
        "stop_on": ("", "What the BPA-L stopping rule tests: `\"vehicles\"` (ours) or `\"vehicles_and_features\"` "
                        "(Sec. V-A as written: also every vehicle's estimate of each feature it observes). The "
                        "Gaussian ICP only; ICP-DA-PF always tests both."),
        "budget_split": ("", "How the consensus exchanges of a step share a `[v2x]` round budget (no effect "
                             "without one): `\"greedy\"` (each takes `consensus_iterations` rounds while any "
                             "are left: a budget below it allows one BPA-L iteration) or `\"even\"` (each takes "
                             "at most the rounds left divided by the exchanges still to come up to "
                             "`bpa_max_iterations`, at least one)."),
    },
    "lc": {
        "eta_threshold": (NO_UNIT, "eta_TH of (30): a track is detected by a vehicle iff b(alpha = 0) < eta_TH "
                                   "(1 = pair every gated measurement, 0.5 = drop ambiguous ones)."),
        "detection_probability": (NO_UNIT, "P_D of a track inside the sensing range; missed-detection weight "
                                           "1 - P_D of (13)."),
        "gate_probability": (NO_UNIT, "Chi-square gate on the 4-D V2F innovation; outside it eta(alpha = l) = 0."),
        "new_feature_velocity_sigma": ("m/s", "Velocity spread of an untracked feature, in the density of a "
                                              "measurement from a new feature."),
        "birth_probability": (NO_UNIT, "A measurement no track took starts a track when its probability of "
                                       "coming from no track is at least this."),
        "merge_gate_m": ("m", "Two tracks closer than this (and within each other's 99 % gate) are merged; "
                              "0 switches merging off."),
        "sensing_range_m": ("m", "The vehicle's own V2F range Rs for candidate tracks (plus a 3-sigma margin); "
                                 "not given: `sensors.v2f_range_m` in force."),
        "new_feature_rate": (NO_UNIT, "mu_new, expected untracked features in a vehicle's view (weight of the "
                                      "new-feature hypothesis)."),
        "new_feature_density": ("1/(m^2 (m/s)^2)", "mu_new f_new(z), the density every eta(alpha = l) of (13) is "
                                                   "divided by, as one constant; 0 = derived: mu_new / (pi Rs^2) "
                                                   "times the velocity density of an untracked feature (about "
                                                   "8.5e-6 at Rs = 75 m); 1 = eta as (13) reads, unnormalised."),
        "pairing": ("", "MAP pairing rule (30): `\"gated\"` (ours: chi-square gate, a contested row goes to the "
                        "larger belief, no threshold test at eta_TH = 1) or `\"paper\"` (literal: ungated, b(alpha "
                        "= 0) < eta_TH at every eta_TH, a row may be taken by several tracks). ICP-DA-PF: "
                        "`\"paper\"` drops its pre-gate."),
        "clutter_intensity": ("1/m^2", "lambda_c, false detections per m^2 per scan the estimator expects (they "
                                       "look like static objects); joins the new-feature density in the "
                                       "normaliser of eta (13). 0 = no clutter (the paper)."),
        "sensor_fov": ("", "P_D per (vehicle, track) from the `[perception]` sensors (field of view around the "
                           "estimated heading, range, detection profile), for ICP-DA-LC and ICP-DA-PF; needs `[perception]`. Off: "
                           "`detection_probability` within the range."),
        "visibility": (NO_UNIT, "With `sensor_fov`: the share of in-view tracks the estimator expects not to be "
                                "occluded (it cannot predict every occluder); scales the sensors' P_D. 1 = no "
                                "occlusion expected, so a miss of an occluded track counts fully against it."),
        "track_existence": ("", "Carry an existence probability with each track (Meyer et al. 2018): a track "
                                "localizes vehicles only while it is at least `confirm_existence`, and is "
                                "dropped below `drop_existence` (ICP-DA-LC and ICP-DA-PF). Off: every track exists (the paper)."),
        "survival_probability": (NO_UNIT, "A track's existence is multiplied by this every step."),
        "confirm_existence": (NO_UNIT, "Existence from which a track localizes vehicles."),
        "drop_existence": (NO_UNIT, "Existence below which a track is dropped."),
        "own_consistency_gate": (NO_UNIT, "Chi-square probability (2 dof): a vehicle whose cooperative position "
                                          "leaves this gate of its own-sensor (GNSS + inertial) track is reset to "
                                          "that track (ICP-DA-LC; ICP-DA-PF under `[fusion]`, with its split "
                                          "filters' own track). 0 = never (the paper)."),
        "relocalize_radius_m": ("m", "ICP-DA-LC: a vehicle with at least `relocalize_min_support` rows and none "
                                     "paired with a confirmed track is relocalized for the association by the "
                                     "unique translation within this radius that puts the most of its rows within "
                                     "`relocalize_tolerance_m` of distinct confirmed tracks (consensus voting, "
                                     "Fischler and Bolles 1981; coloc/methods/lc_reloc.py). 0 = never (the paper)."),
        "relocalize_tolerance_m": ("m", "How close a translated row must come to a confirmed track to support it."),
        "relocalize_min_support": (NO_UNIT, "Rows a vehicle needs for relocalization, and rows on distinct "
                                            "confirmed tracks a translation needs."),
        "relocalize_min_gain": (NO_UNIT, "With `relocalize_radius_m` > 0: a vehicle with rows on confirmed tracks "
                                         "is relocalized too when the vote's translation puts at least this many "
                                         "more of its rows on distinct confirmed tracks than its own mean does "
                                         "(coloc/methods/lc_reloc.py). 0 = lost vehicles only."),
        "reset_map_margin": (NO_UNIT, "With `own_consistency_gate` > 0: a vehicle whose rows land on at least "
                                      "this many more distinct confirmed tracks (within `relocalize_tolerance_m`) "
                                      "from its cooperative position than from its own track's is not reset to "
                                      "its own track: the map arbitrates between the two. 0 = the gate alone "
                                      "decides."),
        "fix_map_margin": (NO_UNIT, "ICP-DA-LC: a vehicle whose motion prediction (before this step's fix) puts "
                                    "at least this many more rows on distinct confirmed tracks (within "
                                    "`relocalize_tolerance_m`) than its belief after the fix is associated at the "
                                    "prediction: the map arbitrates a fix that moves the vehicle off its "
                                    "landmarks. 0 = the association at the belief after the fix (the paper)."),
        "anchor_margin": (NO_UNIT, "ICP-DA-LC: each vehicle keeps a map-anchored position that no fix moves "
                                   "(carried by its velocity, refreshed to its estimate whenever that has rows "
                                   "on at least 2 confirmed tracks); a vehicle whose anchor puts at least "
                                   "max(2, this many more) rows on confirmed tracks than its association mean is "
                                   "associated at its anchor (coloc/methods/lc_reloc.py). 0 = no anchor."),
        "bp_iterations": (NO_UNIT, "BPA-DA iterations (14)-(17), at most."),
        "bp_tol": (NO_UNIT, "BPA-DA stops when its messages change by less than this."),
    },
    "pf": {
        "vehicle_particles": (NO_UNIT, "Jv, particles per vehicle (the paper's single road: 5000)."),
        "feature_particles": (NO_UNIT, "Jf, particles per feature track."),
        "kernel": ("", "Pair sums: `\"tree\"` (k-d tree, exact to kernel_rel_tol per entry, the reference), "
                       "`\"brute\"` or `\"fast\"` (float32 and 16-bit kept matrices, every entry within 1e-3; "
                       "checked against the tree by tools/pf_equivalence.py)."),
        "kernel_rel_tol": (NO_UNIT, "Relative error allowed per entry of a tree pair sum."),
        "kernel_cache_mb": ("MB", "Memory for the kernel matrices kept through BPA-L's iterations (tree: 4 "
                                  "bytes a pair, fast: 2; 0 = none kept)."),
        "min_association_belief": (NO_UNIT, "Options of (18) with a smaller BPA-DA belief are left out of the mixture."),
        "message_bandwidth": ("", "Particle double sums as kernel densities: `\"prior\"` (kernel R + h^2 Cov), "
                                  "`\"shrunk\"` (the same with Liu-West shrunk centres) or `\"none\"` (the bare "
                                  "V2F kernel of (25)-(27))."),
        "recursion": ("", "`\"latest_message\"` (a track keeps each vehicle's latest message) or `\"paper\"` "
                          "(the literal recursion (23)-(24))."),
        "regularize": ("", "Liu-West regularised resampling (static features otherwise never rejuvenate)."),
        "sigma_along": ("m/s^2", "Driving noise of model (1) along the heading for the vehicle particles, in place "
                                 "of `[motion]`'s (absent: `[motion]`'s)."),
        "sigma_cross": ("m/s^2", "The same across the heading. With `[inertial]`, at least the IMU's turn-on bias: "
                                 "the bootstrap PF cannot follow an input error its proposal does not cover."),
        "bpa_stop": ("", "Where BPA-L's stopping rule (Sec. V-A) applies: `\"net\"` (every vehicle and track "
                         "iterates until the whole net has settled, the paper) or `\"component\"` (a connected "
                         "component of BPA-L's graph that has settled stops iterating, the others continue; "
                         "each component ends as if it ran alone under the net rule)."),
    },
    "report": {
        "track_area": ("", "Analysis area of the along/cross-track figure (paper Fig. 18b)."),
        "track_areas": ("", "Several areas, one along/cross-track figure each (the arterial: 2 and 5, paper "
                            "Fig. 18a/b in TLR and Fig. 19 in VSR); give this or track_area."),
        "figures": ("", "Write report.html and figures/*.png after the run."),
    },
    "infra": {
        "rsu_junctions": ("", "Junction ids of the net where RSUs stand (checked against the net file)."),
        "rsu_range_m": ("m", "V2I range of an RSU, equal to its radar range."),
        "radar_sigma_m": ("m", "Radar position noise per axis."),
        "radar_pose_offset_sigma_m": ("m", "Spread of the radar's unknown pose offset, drawn once per run."),
        "odom_sigma_m": ("m", "Odometry noise per axis and step (factor graph)."),
        "rsu_bp_particles": (NO_UNIT, "Particles per vehicle and feature of `rsu_bp`."),
        "rsu_bp_detection_prob": (NO_UNIT, "`rsu_bp`'s P_D of a visible feature."),
        "rsu_bp_feature_drop_s": ("s", "`rsu_bp` drops a feature cloud unseen for this long."),
        "rsu_bp_birth_max_std_m": ("m", "`rsu_bp` starts a feature cloud only from a vehicle whose position "
                                   "standard deviation (per-axis rms of its own covariance) is below this."),
        "sme_max_vehicles": (NO_UNIT, "`sme` skips the radar update when more vehicles are in range."),
        "fg_window_steps": (NO_UNIT, "Window of `fg_topology_new`'s fixed-lag smoother."),
    },
}


# [[estimator_sensors.sensors]] has the keys of [[perception.sensors]].
KEY_DOCS["estimator_sensors.sensors"] = dict(KEY_DOCS["perception.sensors"])
