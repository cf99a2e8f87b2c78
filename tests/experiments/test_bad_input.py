"""The bad-input corpus: every command, every bad input we know of.

Each case runs the command line (in this process, so any uncaught exception fails the test as a
traceback would) and checks: the exit status, exactly one line on stderr that starts with
``coloc: error:`` and names the file and field, and that every file the case had put in its folder
beforehand is untouched and nothing was added. Add a case here for every new bad input.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from couplers.publish import MARKER
from experiments.cli import main
from filetree import snapshot

PROJECT = Path(__file__).resolve().parents[2]
SUMO_GAMES = Path(__import__("sumo").__file__).parent / "tools" / "game"

CONFIG = """
[run]
name = "cross_test"
seed = 1
duration_s = 30.0
methods = ["gnss"]

[scenario]
kind = "sumo"
net_dir = "{net}"
control = "tlr"

[report]
track_area = "3"
{extra}
"""

SWEEP = """
[sweep]
name = "corpus"
base = "cfg.toml"
seeds = {seeds}
methods = ["gnss"]
"""


def _config(tmp: Path, net: Path, extra: str = "", name: str = "cfg.toml") -> Path:
    path = tmp / name
    path.write_text(CONFIG.format(net=net, extra=extra))
    return path


def _user_folder(tmp: Path, name: str = "mywork") -> Path:
    d = tmp / name
    (d / "sub").mkdir(parents=True)
    (d / "thesis.tex").write_text("chapter 1\n")
    (d / "sub" / "data.csv").write_text("1,2\n")
    return d


def _file(tmp: Path, name: str = "notes.txt") -> Path:
    (tmp / name).write_text("my notes\n")
    return tmp / name


def _net_copy(tmp: Path, net: Path) -> Path:
    dst = tmp / "net"
    shutil.copytree(net, dst)
    return dst


def _run_copy(tmp: Path, run_dir: Path) -> Path:
    dst = tmp / "run"
    shutil.copytree(run_dir, dst)
    return dst


@pytest.fixture(scope="module")
def run_dir(cross_net, tmp_path_factory) -> Path:
    """A finished 30 s GNSS run on the test cross (the report cases damage copies of it)."""
    tmp = tmp_path_factory.mktemp("corpus_run")
    cfg = _config(tmp, cross_net)
    assert main(["run", str(cfg), "--out", str(tmp / "run"), "--quiet"]) == 0
    return tmp / "run"


# name -> (setup(tmp, cross_net, run_dir) -> (argv, cwd or None), words the one line must hold)
CASES = {}


def case(*needles: str):
    def deco(fn):
        if fn.__name__ in CASES:  # a second case of one name would hide the first
            raise NameError(f"two bad-input cases are named {fn.__name__}")
        CASES[fn.__name__] = (fn, needles)
        return fn
    return deco


# ----------------------------------------------------------------------------- coloc run: --out


@case("mywork", "--out", "cannot prove it wrote", "--force")
def run_out_user_folder(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(_user_folder(tmp)), "--quiet"], None


@case("notes.txt", "--out", "is a file")
def run_out_file(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(_file(tmp)), "--quiet"], None


@case("notes.txt", "--out", "is a file")
def run_out_file_force(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(_file(tmp)), "--force", "--quiet"], None


@case(".", "--out", "current working folder")
def run_out_cwd(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", ".", "--quiet"], _run_copy(tmp, run)


@case("--out", "current working folder")
def run_out_holds_cwd(tmp, net, run):
    dst = _run_copy(tmp, run)
    return ["run", str(_config(tmp, net)), "--out", str(dst), "--quiet"], dst / "figures"


@case("/proc/coloc-corpus", "--out", "cannot be created")
def run_out_unwritable(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", "/proc/coloc-corpus/run", "--quiet"], None


@case("--out", "holds a coloc sweep output")
def run_out_sweep_folder(tmp, net, run):
    d = tmp / "sw"
    d.mkdir()
    (d / "sweep.toml").write_text("[sweep]\n")
    (d / "runs").mkdir()
    (d / MARKER).write_text('{"kind": "sweep", "files": {}}\n')
    return ["run", str(_config(tmp, net)), "--out", str(d), "--quiet"], None


@case("p", "--out", "cannot prove it wrote", "--force")
def run_out_has_a_runs_file_names(tmp, net, run):
    """A run's file names do not make a folder a run (only its manifest does)."""
    d = tmp / "p"
    (d / "data").mkdir(parents=True)
    (d / "summary.json").write_text("{}\n")
    (d / "config.toml").write_text("x = 1\n")
    (d / "estimates.parquet").write_text("PAR1\n")
    (d / "thesis.tex").write_text("chapter 1\n")
    return ["run", str(_config(tmp, net)), "--out", str(d), "--quiet"], None


@case("run", "--out", "older coloc", "--force")
def run_out_marker_without_file_list(tmp, net, run):
    dst = _run_copy(tmp, run)
    (dst / MARKER).write_text('{"kind": "run"}\n')
    return ["run", str(_config(tmp, net)), "--out", str(dst), "--quiet"], None


@case("run", "--out", "holds a coloc report output")
def run_out_comparison_folder(tmp, net, run):
    dst = _run_copy(tmp, run)
    (dst / MARKER).write_text('{"kind": "report", "files": {}}\n')
    return ["run", str(_config(tmp, net)), "--out", str(dst), "--quiet"], None


@case("report.html", "--out", "cannot prove it wrote it", "--force")
def run_out_file_edited_by_the_user(tmp, net, run):
    """Refused when the run is published (the run's files are known only then): nothing is left behind."""
    dst = _run_copy(tmp, run)
    with open(dst / "report.html", "a") as fh:
        fh.write("<!-- mine -->\n")
    return ["run", str(_config(tmp, net)), "--out", str(dst), "--quiet"], None


@case("figures", "--out", "cannot prove it wrote it")
def run_out_file_where_a_folder_goes(tmp, net, run):
    d = tmp / "o"
    d.mkdir()
    (d / MARKER).write_text('{"kind": "run", "files": {}}\n')
    (d / "figures").write_text("not a folder\n")
    return ["run", str(_config(tmp, net)), "--out", str(d), "--quiet"], None


@case("link", "--out", "symbolic link to", "--force")
def run_out_symbolic_link_to_a_run(tmp, net, run):
    _run_copy(tmp, run)
    (tmp / "link").symlink_to("run")
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "link"), "--quiet"], None


@case("link", "--out", "symbolic link to", "--force")
def run_out_symbolic_link_to_an_empty_folder(tmp, net, run):
    (tmp / "empty").mkdir()
    (tmp / "link").symlink_to("empty")
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "link"), "--quiet"], None


@case("broken", "--out", "broken symbolic link")
def run_out_broken_link(tmp, net, run):
    (tmp / "broken").symlink_to(tmp / "nowhere")
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "broken"), "--quiet"], None


# ----------------------------------------------------------------------------- coloc run: config


@case("cfg.toml", "run.seed", "2147483647")
def run_seed_option_too_large(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "o"), "--seed", str(2**31), "--quiet"], None


@case("cfg.toml", "run.seed", "2147483647")
def run_seed_in_file_too_large(tmp, net, run):
    cfg = _config(tmp, net)
    cfg.write_text(cfg.read_text().replace("seed = 1", f"seed = {2**32}"))
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "run.seed")
def run_seed_negative(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "o"), "--seed", "-1", "--quiet"], None


@case("cfg.toml", "run.seed", "expected an integer")
def run_seed_not_integer(tmp, net, run):
    cfg = _config(tmp, net)
    cfg.write_text(cfg.read_text().replace("seed = 1", 'seed = "one"'))
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "sensors.v2f_range_m", "must be positive")
def run_v2f_range_zero(tmp, net, run):
    cfg = _config(tmp, net, "[sensors]\nv2f_range_m = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_da_lc", "--quiet"], None


@case("cfg.toml", "sensors.v2f_range_m", "must be positive")
def run_v2f_range_negative(tmp, net, run):
    cfg = _config(tmp, net, "[sensors]\nv2f_range_m = -5.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_da_lc", "--quiet"], None


@case("sr.toml", "single_road.v2f_range_m", "must be positive")
def run_scenario_v2f_range_zero(tmp, net, run):
    text = (PROJECT / "experiments" / "single_road.toml").read_text()
    path = tmp / "sr.toml"
    path.write_text(text.replace("v2f_range_m = 50.0", "v2f_range_m = 0.0"))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "lc.pairing", "gated")
def run_unknown_pairing_rule(tmp, net, run):
    cfg = _config(tmp, net, '[lc]\npairing = "literal"\n')
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_da_lc", "--quiet"], None


def _lc_run(tmp, net, lc_table: str):
    """``coloc run`` of gnss and icp_da_lc on a config with this ``[lc]`` table."""
    cfg = _config(tmp, net, lc_table)
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_da_lc", "--quiet"], None


@case("cfg.toml", "lc.new_feature_density", ">= 0")
def run_negative_new_feature_density(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\nnew_feature_density = -1e-5\n")


@case("cfg.toml", "lc.sensor_fov", "[perception]")
def run_sensor_fov_without_perception(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\nsensor_fov = true\n")


@case("cfg.toml", "lc.confirm_existence", "drop_existence")
def run_existence_thresholds_crossed(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\ntrack_existence = true\nconfirm_existence = 0.005\n")


@case("cfg.toml", "lc.relocalize_tolerance_m")
def run_relocalize_tolerance_zero(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\nrelocalize_radius_m = 10.0\nrelocalize_tolerance_m = 0.0\n")


@case("cfg.toml", "lc.relocalize_min_support")
def run_relocalize_min_support_zero(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\nrelocalize_radius_m = 10.0\nrelocalize_min_support = 0\n")


@case("cfg.toml", "lc.relocalize_min_gain")
def run_relocalize_min_gain_negative(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\nrelocalize_radius_m = 10.0\nrelocalize_min_gain = -1\n")


@case("cfg.toml", "lc.reset_map_margin")
def run_reset_map_margin_negative(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\nown_consistency_gate = 0.9999\nreset_map_margin = -2\n")


@case("cfg.toml", "lc.anchor_margin")
def run_anchor_margin_negative(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\nanchor_margin = -1\n")


@case("cfg.toml", "lc.fix_map_margin")
def run_fix_map_margin_negative(tmp, net, run):
    return _lc_run(tmp, net, "[lc]\nfix_map_margin = -1\n")


@case("cfg.toml", "icp.stop_on", "vehicles_and_features")
def run_unknown_stop_rule(tmp, net, run):
    cfg = _config(tmp, net, '[icp]\nstop_on = "features"\n')
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_known_da", "--quiet"], None


@case("cfg.toml", "report.track_areas", "not both")
def run_track_area_and_areas(tmp, net, run):
    cfg = _config(tmp, net)
    cfg.write_text(cfg.read_text().replace('track_area = "3"', 'track_area = "3"\ntrack_areas = ["1", "2"]'))
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("sr.toml", "single_road.start", "gnss_fix")
def run_unknown_start(tmp, net, run):
    text = (PROJECT / "experiments" / "single_road.toml").read_text()
    path = tmp / "sr.toml"
    path.write_text(text.replace("[single_road]\n", '[single_road]\nstart = "cold"\n'))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("cr.toml", "crossroad.prior_sigma_p", "gnss_fix")
def run_prior_sigma_with_gnss_fix(tmp, net, run):
    text = (PROJECT / "experiments" / "crossroad.toml").read_text()
    path = tmp / "cr.toml"
    path.write_text(text.replace("[crossroad]\n", '[crossroad]\nstart = "gnss_fix"\nprior_sigma_p = 3.0\n'))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "run.duration_s", "no vehicle was in the network")
def run_duration_too_short(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "o"), "--duration", "1e-9", "--quiet"], None


@case("cfg.toml", "run.duration_s", "must be positive")
def run_duration_zero(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "o"), "--duration", "0", "--quiet"], None


@case("cfg.toml", "motion.sigma_sideways", "unknown")
def run_unknown_key(tmp, net, run):
    return ["run", str(_config(tmp, net, "[motion]\nsigma_sideways = 1.0\n")), "--out", str(tmp / "o")], None


@case("cfg.toml", "run.methods[1]", "magic")
def run_unknown_method(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "o"), "--methods", "gnss,magic"], None


@case("cfg.toml", "nonsense", "unknown table")
def run_unknown_table(tmp, net, run):
    return ["run", str(_config(tmp, net, "[nonsense]\nx = 1\n")), "--out", str(tmp / "o")], None


@case("cfg.toml", "not valid TOML")
def run_broken_toml(tmp, net, run):
    cfg = _config(tmp, net)
    cfg.write_text(cfg.read_text().replace("[run]", "[run\n"))
    return ["run", str(cfg), "--out", str(tmp / "o")], None


@case("nope.toml", "config file not found")
def run_missing_config(tmp, net, run):
    return ["run", str(tmp / "nope.toml"), "--out", str(tmp / "o")], None


@case("cfg.toml", "scenario.control")
def run_unknown_control(tmp, net, run):
    cfg = _config(tmp, net)
    cfg.write_text(cfg.read_text().replace('control = "tlr"', 'control = "allgreen"'))
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("scenario.toml", "files.net")
def run_missing_net_file(tmp, net, run):
    copy = _net_copy(tmp, net)
    (copy / "tlr.net.xml").unlink()
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("zones.geojson", "uncovered")
def run_zones_leave_lanes_uncovered(tmp, net, run):
    copy = _net_copy(tmp, net)
    zones = json.loads((copy / "zones.geojson").read_text())
    zones["features"] = zones["features"][:1]
    (copy / "zones.geojson").write_text(json.dumps(zones))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("demand.rou.xml", "'nosuchedge' is not in the net")
def run_route_over_unknown_edge(tmp, net, run):
    copy = _net_copy(tmp, net)
    routes = copy / "demand.rou.xml"
    routes.write_text(routes.read_text().replace('edges="WC CE"', 'edges="nosuchedge WC CE"', 1))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


UNSORTED = """<routes>
  <vType id="car"/>
  <route id="we" edges="WC CE"/>
  <vehicle id="late" type="car" route="we" depart="100"/>
  <vehicle id="early" type="car" route="we" depart="5"/>
  <vehicle id="v2" type="car" route="we" depart="8"/>
</routes>
"""


@case("demand.rou.xml", "depart", "not sorted by departure", "'early'", "'late'")
def run_routes_not_sorted(tmp, net, run):
    copy = _net_copy(tmp, net)
    (copy / "demand.rou.xml").write_text(UNSORTED)
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("features.add.xml", "from the nearest drivable lane")
def run_feature_far_from_roads(tmp, net, run):
    copy = _net_copy(tmp, net)
    feats = copy / "features.add.xml"
    text = feats.read_text()
    i = text.index(' y="', text.index("<poi"))
    j = text.index('"', i + 4)
    feats.write_text(text[:i] + ' y="4612.0' + text[j:])
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.sensors[0].fov_deg")
def run_perception_fov_out_of_range(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\n[[perception.sensors]]\nfov_deg = 361.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.occlusion_buildings", "has no buildings", "set it false")
def run_building_occlusion_without_buildings(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\nocclusion_buildings = true\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("mine.toml", "perception.occlusion_buildings", "has no buildings")
def run_realistic_preset_on_net_without_buildings(tmp, net, run):
    # the preset's true is inherited; the error names the file that chose the net folder
    (tmp / "mine.toml").write_text(f'extends = "{PROJECT / "experiments" / "arterial_tlr_realistic.toml"}"\n'
                                   f'[run]\nname = "mine"\n[scenario]\nnet_dir = "{net}"\n'
                                   '[report]\ntrack_areas = ["3"]\n')
    return ["run", str(tmp / "mine.toml"), "--out", str(tmp / "o"), "--quiet"], None


@case("--occlusion-s", "-1", ">= 0")
def net_import_occlusion_negative(tmp, net, run):
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--name", "x", "--out", str(tmp / "x"),
            "--experiments-dir", str(tmp / "exps"), "--occlusion-s", "-1"], None


@case("cfg.toml", "perception.sensors[1].pd_near")
def run_perception_probability_out_of_range(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\n[[perception.sensors]]\nname = 'a'\n[[perception.sensors]]\npd_near = 1.5\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.persistent_clutter_pd")
def run_perception_persistent_pd_out_of_range(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\npersistent_clutter_per_km = 5.0\npersistent_clutter_pd = 1.2\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.persistent_clutter_per_km")
def run_perception_negative_persistent_density(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\npersistent_clutter_per_km = -2.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.class_error")
def run_perception_class_error_out_of_range(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\nclass_error = 2.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.road_users")
def run_perception_road_users_not_bool(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\nroad_users = 1\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "estimator_sensors.sensors[0].range_m")
def run_estimator_sensors_bad_range(tmp, net, run):
    cfg = _config(tmp, net, "[estimator_sensors]\n[[estimator_sensors.sensors]]\nrange_m = -5.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "estimator_sensors.sensors")
def run_estimator_sensors_without_sensors(tmp, net, run):
    cfg = _config(tmp, net, "[estimator_sensors]\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.sensors[0].clutter_per_scan")
def run_perception_negative_clutter(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\n[[perception.sensors]]\nclutter_per_scan = -1.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.detections", "range_bearing")
def run_perception_unknown_detection_kind(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\ndetections = 'polar'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.lever_arm_range_rate", "range_bearing")
def run_perception_lever_arm_without_sensor_frame(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\nlever_arm_range_rate = true\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.sensors[0].sigma_b_deg")
def run_perception_negative_bearing_sigma(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\ndetections = 'range_bearing'\n[[perception.sensors]]\nsigma_b_deg = -0.3\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "perception.sensors[0].sigma_r_m")
def run_perception_zero_range_sigma(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\ndetections = 'range_bearing'\n[[perception.sensors]]\nsigma_r_m = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.tau_s")
def run_gnss_error_negative_tau(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\ntau_s = -5.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.common_share", "[0, 1]")
def run_gnss_error_share_above_one(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'field'\ncommon_share = 1.5\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.field_share", "[0, 1]")
def run_gnss_error_negative_share(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'field'\nfield_share = -0.1\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.local_corr_length_m", "positive")
def run_gnss_error_negative_correlation_length(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'field'\nlocal_corr_length_m = -20.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.field_corr_length_m", "positive")
def run_gnss_error_zero_field_length(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'field'\nfield_corr_length_m = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.model", "per_vehicle")
def run_gnss_error_unknown_model(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'rinex'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.elevation_mask_deg", "[0, 90)")
def run_gnss_satellites_mask_at_zenith(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'satellites'\nelevation_mask_deg = 90.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.elevation_mask_deg", "[0, 90)")
def run_gnss_satellites_mask_below_horizon(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'satellites'\nelevation_mask_deg = -5.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.nlos", "block")
def run_gnss_satellites_unknown_nlos(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'satellites'\nnlos = 'mirror'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.velocity", "doppler")
def run_gnss_satellites_unknown_velocity(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'satellites'\nvelocity = 'radar'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.reported_covariance", "residual")
def run_gnss_satellites_unknown_reported_covariance(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'satellites'\nreported_covariance = 'raim'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.draws", "visible")
def run_gnss_satellites_unknown_draws(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'satellites'\ndraws = 'some'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.rx_doppler_mps")
def run_gnss_satellites_zero_doppler_budget(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'satellites'\nvelocity = 'doppler'\nrx_doppler_mps = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.doppler_noise_mps")
def run_gnss_satellites_negative_doppler_noise(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nmodel = 'satellites'\ndoppler_noise_mps = -0.1\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("buildings.geojson", "features[1].properties.height", "satellites")
def run_gnss_satellites_building_without_height(tmp, net, run):
    copy = _net_copy(tmp, net)
    doc = {"type": "FeatureCollection", "crs": {"type": "name", "properties": {"name": "urn:coloc:sumo-net-xy"}},
           "features": [{"type": "Feature", "properties": {"height": h},
                         "geometry": {"type": "Polygon", "coordinates": [[[x, 20], [x + 10, 20], [x + 10, 30],
                                                                          [x, 30], [x, 20]]]}}
                        for x, h in ((0.0, 12.0), (40.0, None))]}
    doc["features"][1]["properties"] = {}
    (copy / "buildings.geojson").write_text(json.dumps(doc))
    cfg = _config(tmp, copy, "[gnss_error]\nmodel = 'satellites'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "scenario.start", "gnss_fix")
def run_unknown_sumo_start(tmp, net, run):
    path = tmp / "cfg.toml"
    path.write_text(CONFIG.format(net=net, extra="").replace('control = "tlr"', 'control = "tlr"\nstart = "truth"'))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "scenario.reference_point", "centre")
def run_unknown_reference_point(tmp, net, run):
    path = tmp / "cfg.toml"
    path.write_text(CONFIG.format(net=net, extra="").replace('control = "tlr"',
                                                              'control = "tlr"\nreference_point = "rear_axle"'))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("sr.toml", "scenario.reference_point", "only for scenario.kind")
def run_reference_point_without_sumo(tmp, net, run):
    text = (PROJECT / "experiments" / "single_road.toml").read_text()
    path = tmp / "sr.toml"
    path.write_text(text.replace("[scenario]\n", '[scenario]\nreference_point = "centre"\n'))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "inertial.accel_noise_density", ">= 0")
def run_inertial_negative_noise(tmp, net, run):
    cfg = _config(tmp, net, "[inertial]\naccel_noise_density = -0.004\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "inertial.gyro_bias_tau_s", "positive")
def run_inertial_zero_correlation_time(tmp, net, run):
    cfg = _config(tmp, net, "[inertial]\ngyro_bias_tau_s = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "inertial.gyro_turn_on_sigma", "number")
def run_inertial_text_value(tmp, net, run):
    cfg = _config(tmp, net, "[inertial]\ngyro_turn_on_sigma = 'half a degree'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "inertial.yaw_noise", "unknown key")
def run_inertial_unknown_key(tmp, net, run):
    cfg = _config(tmp, net, "[inertial]\nyaw_noise = 0.1\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "sensors.inertial", "[inertial] table")
def run_inertial_inside_sensors(tmp, net, run):
    cfg = _config(tmp, net, "[sensors]\ninertial = 1\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "inertial", "[infra]")
def run_inertial_with_infra(tmp, net, run):
    cfg = _config(tmp, net, "[infra]\n[inertial]\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("single_road.toml", "inertial", "sumo")
def run_inertial_controlled_scenario(tmp, net, run):
    cfg = tmp / "single_road.toml"
    cfg.write_text((PROJECT / "experiments" / "single_road.toml").read_text() + "\n[inertial]\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "pf", "bpa_stop", "net, component")
def run_pf_bpa_stop_unknown(tmp, net, run):
    return ["run", str(_config(tmp, net, "[pf]\nbpa_stop = \"track\"\n")), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "features.pedestrians", "persons")
def run_pedestrians_on_a_net_without_persons(tmp, net, run):
    cfg = _config(tmp, net, "[features]\npedestrians = true\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "features.pedestrians", "true or false")
def run_pedestrians_not_a_boolean(tmp, net, run):
    cfg = _config(tmp, net, "[features]\npedestrians = \"yes\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "run.methods[1]", "icp_da_pf", "pedestrians")
def run_pedestrians_with_a_method_without_classes(tmp, net, run):
    cfg = _config(tmp, PROJECT / "sumo_nets" / "arterial_ped", "[features]\npedestrians = true\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_da_pf", "--quiet"], None


@case("cfg.toml", "features.pedestrians", "sumo")
def run_pedestrians_on_a_controlled_scenario(tmp, net, run):
    cfg = tmp / "cfg.toml"
    cfg.write_text('[run]\nname = "x"\nmethods = ["gnss"]\n[scenario]\nkind = "crossroad"\n'
                   "[features]\npedestrians = true\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "icp.pedestrian_sigma_par", "positive")
def run_negative_pedestrian_noise(tmp, net, run):
    cfg = _config(tmp, net, "[icp]\npedestrian_sigma_par = -0.1\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("scenario.toml", "files.persons", "not found")
def run_net_folder_persons_file_missing(tmp, net, run):
    dst = _net_copy(tmp, net)
    scen = dst / "scenario.toml"
    scen.write_text(scen.read_text().replace("[files]\n", "[files]\npersons = \"walkers.rou.xml\"\n", 1))
    return ["run", str(_config(tmp, dst)), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.penetration_rate", "none of them was equipped")
def run_v2x_no_vehicle_equipped(tmp, net, run):
    # vehicles drive through the cross in the 30 s, but at 0.1 % penetration none has a V2X unit
    cfg = _config(tmp, net, "[v2x]\npenetration_rate = 0.001\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.penetration_rate", "(0, 1]")
def run_v2x_penetration_zero(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\npenetration_rate = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.penetration_rate", "(0, 1]")
def run_v2x_penetration_above_one(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\npenetration_rate = 1.5\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.pdr_los[2]", "must not increase")
def run_v2x_delivery_increasing_with_distance(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\npdr_distance_m = [0.0, 100.0, 200.0]\npdr_los = [1.0, 0.5, 0.6]\n"
                            "pdr_nlos = [0.5, 0.2, 0.0]\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.pdr_nlos[0]", "[0, 1]")
def run_v2x_delivery_above_one(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\npdr_distance_m = [0.0, 100.0]\npdr_los = [1.0, 0.5]\npdr_nlos = [1.2, 0.2]\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.pdr_distance_m[1]", "increase")
def run_v2x_distances_not_increasing(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\npdr_distance_m = [100.0, 50.0]\npdr_los = [1.0, 0.5]\npdr_nlos = [1.0, 0.2]\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "lc", "visibility")
def run_lc_visibility_zero(tmp, net, run):
    cfg = _config(tmp, net, "[lc]\nvisibility = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "motion.imu_heading", "dead_reckoned, held")
def run_unknown_imu_heading(tmp, net, run):
    cfg = _config(tmp, net, "[motion]\nimu_heading = \"gyro\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "icp.budget_split", "greedy, even")
def run_icp_unknown_budget_split(tmp, net, run):
    cfg = _config(tmp, net, "[icp]\nbudget_split = \"fair\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "pf", "sigma_along and sigma_cross must be positive")
def run_pf_driving_noise_zero(tmp, net, run):
    cfg = _config(tmp, net, "[pf]\nsigma_cross = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.channel", "curves, ideal")
def run_v2x_unknown_channel(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\nchannel = \"perfect\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("sweep.toml", "sweep.factors.x[0]", "the preset level takes no set, base or relative")
def sweep_factor_preset_with_overrides(tmp, net, run):
    path = _sweep(tmp, net)
    path.write_text(path.read_text() + '\n[sweep.factors]\nx = [{label = "a", preset = true, '
                                       'set = {"lc.eta_threshold" = 1.0}}]\n')
    return ["sweep", str(path), "--out", str(tmp / "o"), "--quiet", "--workers", "1"], None


@case("cfg.toml", "v2x.pdr_nlos", "one value per distance")
def run_v2x_lists_of_different_length(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\npdr_distance_m = [0.0, 100.0]\npdr_los = [1.0, 0.5]\npdr_nlos = [1.0]\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.rounds_per_step", ">= 1")
def run_v2x_negative_rounds(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\nrounds_per_step = -1\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.rounds_per_step", ">= 1")
def run_v2x_zero_rounds(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\nrounds_per_step = 0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.rounds_per_step", "unlimited")
def run_v2x_rounds_misspelt(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\nrounds_per_step = \"infinite\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "v2x.rounds_per_step", "integer")
def run_v2x_fractional_rounds(tmp, net, run):
    cfg = _config(tmp, net, "[v2x]\nrounds_per_step = 2.5\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("single_road.toml", "v2x", "sumo")
def run_v2x_controlled_scenario(tmp, net, run):
    cfg = tmp / "single_road.toml"
    cfg.write_text((PROJECT / "experiments" / "single_road.toml").read_text() + "\n[v2x]\npenetration_rate = 0.5\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("buildings.geojson")
def run_buildings_file_not_geojson(tmp, net, run):
    copy = _net_copy(tmp, net)
    (copy / "buildings.geojson").write_text("{not json")
    return ["run", str(_config(tmp, copy, "[perception]\n")), "--out", str(tmp / "o"), "--quiet"], None


@case("sme.toml", "study.seed", "2147483647")
def run_study_seed_too_large(tmp, net, run):
    return ["run", str(PROJECT / "experiments" / "sme.toml"), "--out", str(tmp / "o"), "--seed", str(2**31),
            "--quiet"], None


# ----------------------------------------------------------------------------- coloc run: numbers out of range


def _zones_sigma(tmp: Path, net: Path, value: str) -> Path:
    copy = _net_copy(tmp, net)
    zones = copy / "zones.geojson"
    zones.write_text(zones.read_text().replace('"sigma_p": 3.0', f'"sigma_p": {value}', 1))
    return copy


@case("zones.geojson", "features[0].properties.sigma_p", "inf m is outside (0, 1000] m")
def run_zones_sigma_infinity(tmp, net, run):
    return ["run", str(_config(tmp, _zones_sigma(tmp, net, "Infinity"))), "--out", str(tmp / "o"), "--quiet"], None


@case("zones.geojson", "features[0].properties.sigma_p", "1e+308 m is outside (0, 1000] m")
def run_zones_sigma_huge(tmp, net, run):
    return ["run", str(_config(tmp, _zones_sigma(tmp, net, "1e308"))), "--out", str(tmp / "o"), "--quiet"], None


@case("zones.geojson", "features[0].properties.sigma_v", "not a positive number")
def run_zones_sigma_v_nan(tmp, net, run):
    copy = _net_copy(tmp, net)
    zones = copy / "zones.geojson"
    zones.write_text(zones.read_text().replace('"sigma_v": 0.1', '"sigma_v": NaN', 1))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("zones.geojson", "features[0].geometry", "not finite")
def run_zones_vertex_nan(tmp, net, run):
    copy = _net_copy(tmp, net)
    zones = copy / "zones.geojson"
    zones.write_text(zones.read_text().replace("[0, -500], [0, 500]", "[0, -500], [NaN, 500]", 1))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "motion.sigma_along", "1e+308 m/s^2 is outside [0, 50] m/s^2")
def run_motion_sigma_huge(tmp, net, run):
    return ["run", str(_config(tmp, net, "[motion]\nsigma_along = 1e308\n")), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_error.nlos_bias_mean_m", "1e+308 m is outside [0, 1000] m")
def run_gnss_error_bias_huge(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_error]\nnlos_bias_mean_m = 1e308\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "inertial.accel_turn_on_sigma", "1e+308 m/s^2 is outside [0, 50] m/s^2")
def run_inertial_turn_on_huge(tmp, net, run):
    cfg = _config(tmp, net, "[inertial]\naccel_turn_on_sigma = 1e308\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "lc.bp_iterations", "100000000000000000000 is outside [0, 100000]")
def run_iterations_beyond_int64(tmp, net, run):
    # TOML integers are 64-bit; Python's reader takes 1e20 as an int all the same: refused by its range.
    return _lc_run(tmp, net, "[lc]\nbp_iterations = 100000000000000000000\n")


@case("cfg.toml", "icp.consensus_iterations", "is outside [0, 100000]")
def run_consensus_iterations_huge(tmp, net, run):
    cfg = _config(tmp, net, "[icp]\nconsensus_iterations = 1000000000\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_known_da", "--quiet"], None


@case("cfg.toml", "pf.vehicle_particles", "1000000000000 is outside [1, 100000]", "24 GB")
def run_particles_huge(tmp, net, run):
    cfg = _config(tmp, net, "[pf]\nvehicle_particles = 1000000000000\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_da_pf", "--quiet"], None


@case("cfg.toml", "perception.sensors[0].range_m", "1e+200 m is outside [0, 10000] m")
def run_perception_range_huge(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\n[[perception.sensors]]\nrange_m = 1e200\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "sensors.v2f_range_m", "1e+200 m is outside")
def run_v2f_range_huge(tmp, net, run):
    cfg = _config(tmp, net, "[sensors]\nv2f_range_m = 1e200\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--methods", "gnss,icp_da_lc", "--quiet"], None


@case("cfg.toml", "perception.sensors[0].clutter_per_scan", "1e+06 is outside [0, 1000]")
def run_perception_clutter_huge(tmp, net, run):
    cfg = _config(tmp, net, "[perception]\n[[perception.sensors]]\nclutter_per_scan = 1e6\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "run.duration_s", "is outside [0, 604800] s")
def run_duration_beyond_a_week(tmp, net, run):
    return ["run", str(_config(tmp, net)), "--out", str(tmp / "o"), "--duration", "1e9", "--quiet"], None


@case("cr.toml", "crossroad.centre[0]", "is outside [-1e+07, 1e+07] m")
def run_crossroad_centre_far_away(tmp, net, run):
    text = (PROJECT / "experiments" / "crossroad.toml").read_text()
    path = tmp / "cr.toml"
    path.write_text(text.replace("centre = [0.0, 0.0]", "centre = [1e12, 0.0]"))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("features.add.xml", "poi[0].x/y", "not finite")
def run_feature_coordinate_nan(tmp, net, run):
    copy = _net_copy(tmp, net)
    feats = copy / "features.add.xml"
    feats.write_text(feats.read_text().replace('x="-350.0"', 'x="nan"', 1))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("features.add.xml", "poi[0].x/y", "outside the net's boundary")
def run_feature_millions_of_metres_away(tmp, net, run):
    copy = _net_copy(tmp, net)
    feats = copy / "features.add.xml"
    feats.write_text(feats.read_text().replace('x="-350.0"', 'x="-3500000.0"', 1))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("demand.rou.xml", "flow[0].begin", "nan s is outside")
def run_route_depart_nan(tmp, net, run):
    copy = _net_copy(tmp, net)
    routes = copy / "demand.rou.xml"
    routes.write_text(routes.read_text().replace('begin="0"', 'begin="nan"', 1))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("demand.rou.xml", "vehicle[0].depart", "-5 s is outside")
def run_route_depart_negative(tmp, net, run):
    copy = _net_copy(tmp, net)
    routes = copy / "demand.rou.xml"
    routes.write_text(routes.read_text().replace("</routes>", '<vehicle id="v" route="we" depart="-5"/></routes>'))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("walkers.rou.xml", "personFlow[0].departPos", "inf m is outside")
def run_person_position_infinite(tmp, net, run):
    copy = _net_copy(tmp, net)
    (copy / "walkers.rou.xml").write_text('<routes><personFlow id="p" begin="0" end="60" period="10" '
                                          'departPos="inf"><walk edges="WC CE"/></personFlow></routes>\n')
    scen = copy / "scenario.toml"
    scen.write_text(scen.read_text().replace("[files]\n", "[files]\npersons = \"walkers.rou.xml\"\n", 1))
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("scenario.toml", "sumo.step_length", "expected a finite number")
def run_net_scenario_value_nan(tmp, net, run):
    copy = _net_copy(tmp, net)
    scen = copy / "scenario.toml"
    scen.write_text(scen.read_text() + "[sumo]\nstep_length = nan\n")
    return ["run", str(_config(tmp, copy)), "--out", str(tmp / "o"), "--quiet"], None


@case("sme.toml", "study.runs", "1000000000000 is outside [1, 100000]")
def run_study_runs_huge(tmp, net, run):
    path = tmp / "sme.toml"
    path.write_text((PROJECT / "experiments" / "sme.toml").read_text().replace("runs = 200", "runs = 1000000000000"))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("rsu_bp.toml", "study.scenario.gnss_var[1]", "1e+300 m^2 is outside")
def run_study_variance_infinite(tmp, net, run):
    path = tmp / "rsu_bp.toml"
    path.write_text((PROJECT / "experiments" / "rsu_bp.toml").read_text().replace("[0.01, 15.0]", "[0.01, 1e300]"))
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


# ----------------------------------------------------------------------------- coloc report


@case("summary.json", "not valid JSON")
def report_corrupt_summary(tmp, net, run):
    dst = _run_copy(tmp, run)
    (dst / "summary.json").write_text("{bad")
    return ["report", str(dst)], None


@case("summary.json", "expected a JSON object")
def report_summary_not_an_object(tmp, net, run):
    dst = _run_copy(tmp, run)
    (dst / "summary.json").write_text("[1, 2]")
    return ["report", str(dst)], None


@case("estimates.parquet", "not a readable Parquet file")
def report_truncated_estimates(tmp, net, run):
    dst = _run_copy(tmp, run)
    data = (dst / "estimates.parquet").read_bytes()
    (dst / "estimates.parquet").write_bytes(data[: len(data) // 2])
    return ["report", str(dst)], None


@case("traffic.parquet", "not a readable Parquet file")
def report_truncated_traffic(tmp, net, run):
    dst = _run_copy(tmp, run)
    (dst / "traffic.parquet").write_bytes(b"PAR1")
    return ["report", str(dst)], None


@case("config.toml", "not valid TOML")
def report_corrupt_config(tmp, net, run):
    dst = _run_copy(tmp, run)
    (dst / "config.toml").write_text("x\n")
    return ["report", str(dst)], None


@case("mywork", "holds no coloc run output", "summary.json")
def report_not_a_run_folder(tmp, net, run):
    return ["report", str(_user_folder(tmp))], None


def _drop_columns(path: Path, *names: str) -> None:
    import pyarrow.parquet as pq

    pq.write_table(pq.read_table(path).drop(list(names)), path)


@case("estimates.parquet", "missing column err_pos")
def report_estimates_column_removed(tmp, net, run):
    dst = _run_copy(tmp, run)
    _drop_columns(dst / "estimates.parquet", "err_pos")
    return ["report", str(dst)], None


@case("estimates.parquet", "missing columns method, t, err_pos")
def report_estimates_of_another_tool(tmp, net, run):
    import pandas as pd

    dst = _run_copy(tmp, run)
    pd.DataFrame({"time": [0.0, 0.1], "x": [1.0, 2.0]}).to_parquet(dst / "estimates.parquet")
    return ["report", str(dst)], None


@case("traffic.parquet", "missing column interval_start_s")
def report_traffic_column_removed(tmp, net, run):
    dst = _run_copy(tmp, run)
    _drop_columns(dst / "traffic.parquet", "interval_start_s")
    return ["report", str(dst)], None


@case("estimates.parquet", "missing column t")
def report_compare_estimates_column_removed(tmp, net, run):
    dst = _run_copy(tmp, run)
    _drop_columns(dst / "estimates.parquet", "t")
    other = tmp / "run2"
    shutil.copytree(run, other)
    return ["report", str(other), str(dst), "--out", str(tmp / "cmp")], None


@case("curves.parquet", "missing column rmse_pos_m")
def report_sweep_curves_column_removed(tmp, net, run):
    import pandas as pd

    d = tmp / "sw"
    d.mkdir()
    (d / "sweep.toml").write_text('[sweep]\nname = "s"\nseeds = [1]\nmethods = ["gnss"]\n')
    pd.DataFrame({"run_id": ["seed=1"]}).to_parquet(d / "sweep.parquet")
    pd.DataFrame({"curve": ["overall"], "method": ["gnss"], "x": [float("nan")], "n_runs": [1], "n_samples": [3],
                  "rmse_vel_mps": [0.1], "correct_pct": [float("nan")], "wrong_pct": [float("nan")],
                  "discarded_pct": [float("nan")]}).to_parquet(d / "curves.parquet")
    return ["report", str(d)], None


@case("notes.txt", "is a file, not a run output folder")
def report_a_file(tmp, net, run):
    return ["report", str(_file(tmp))], None


@case("runs", "2 run folder(s) in it", "give those")
def report_a_folder_of_runs(tmp, net, run):
    d = tmp / "runs"
    d.mkdir()
    for name in ("seed=1", "seed=2"):
        shutil.copytree(run, d / name)
    return ["report", str(d)], None


@case("sw", "holds a coloc sweep output, not a run output")
def report_a_sweep_beside_a_run(tmp, net, run):
    d = tmp / "sw"
    d.mkdir()
    (d / MARKER).write_text('{"kind": "sweep"}\n')
    (d / "sweep.toml").write_text("[sweep]\n")
    return ["report", str(d), str(_run_copy(tmp, run)), "--out", str(tmp / "cmp")], None


@case("run", "summary.json", "missing: the run folder is incomplete")
def report_an_incomplete_run(tmp, net, run):
    dst = _run_copy(tmp, run)
    (dst / "summary.json").unlink()
    return ["report", str(dst)], None


@case("mywork", "--out", "cannot prove it wrote")
def report_out_user_folder(tmp, net, run):
    return ["report", str(_run_copy(tmp, run)), "--out", str(_user_folder(tmp))], None


@case("compare", "--out", "cannot prove it wrote", "--force")
def report_default_out_user_folder(tmp, net, run):
    """``coloc report A B`` writes ``A/../compare`` by default: a user's folder of that name is not taken."""
    a = _run_copy(tmp, run)
    b = tmp / "run2"
    shutil.copytree(run, b)
    (tmp / "compare" / "figures").mkdir(parents=True)
    (tmp / "compare" / "report.html").write_text("<p>mine</p>\n")
    (tmp / "compare" / "figures" / "my_plot.png").write_bytes(b"my plot")
    return ["report", str(a), str(b)], None


@case("link", "--out", "symbolic link to", "--force")
def report_out_symbolic_link(tmp, net, run):
    (tmp / "cmp").mkdir()
    (tmp / "link").symlink_to("cmp")
    return ["report", str(_run_copy(tmp, run)), "--out", str(tmp / "link")], None


@case("traffic.png", "cannot prove it wrote it", "--force")
def report_figure_edited_by_the_user(tmp, net, run):
    dst = _run_copy(tmp, run)
    (dst / "figures" / "traffic.png").write_bytes(b"my own traffic figure")
    return ["report", str(dst)], None


@case("notes.txt", "--out", "is a file")
def report_out_file(tmp, net, run):
    return ["report", str(_run_copy(tmp, run)), "--out", str(_file(tmp)), "--force"], None


@case("/proc/coloc-corpus", "--out", "cannot be created")
def report_out_unwritable(tmp, net, run):
    return ["report", str(_run_copy(tmp, run)), "--out", "/proc/coloc-corpus"], None


# ----------------------------------------------------------------------------- coloc sweep


def _sweep(tmp: Path, net: Path, seeds: str = "[1, 2]") -> Path:
    _config(tmp, net)
    path = tmp / "sweep.toml"
    path.write_text(SWEEP.format(seeds=seeds))
    return path


@case("notes.txt", "--out", "is a file")
def sweep_out_file(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net)), "--out", str(_file(tmp)), "--quiet"], None


@case("mywork", "--out", "cannot prove it wrote")
def sweep_out_user_folder(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net)), "--out", str(_user_folder(tmp)), "--quiet"], None


@case("--out", "holds a coloc run output")
def sweep_out_run_folder(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net)), "--out", str(_run_copy(tmp, run)), "--quiet"], None


@case("/proc/coloc-corpus", "--out", "cannot be created")
def sweep_out_unwritable(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net)), "--out", "/proc/coloc-corpus", "--quiet", "--workers", "1"], None


@case("--scheduler", "notanaddress")
def sweep_scheduler_not_an_address(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net)), "--out", str(tmp / "o"), "--scheduler", "notanaddress", "--quiet"], None


@case("sweep.toml", "sweep.seeds.count", "2147483647")
def sweep_seed_range_too_large(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net, "{start = 2147483647, count = 2}")), "--out", str(tmp / "o"),
            "--dry-run"], None


@case("sweep.toml", "sweep.seeds[1]", "2147483647")
def sweep_seed_list_too_large(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net, f"[1, {2**31}]")), "--out", str(tmp / "o"), "--dry-run"], None


@case("sweep.toml", "sweep.grid.motion.sigma_along[1]", "1e+308 m/s^2 is outside [0, 50] m/s^2")
def sweep_grid_value_out_of_range_dry_run(tmp, net, run):
    path = _sweep(tmp, net)
    path.write_text(path.read_text() + '\n[sweep.grid]\n"motion.sigma_along" = [0.35, 1e308]\n')
    return ["sweep", str(path), "--out", str(tmp / "o"), "--dry-run"], None


@case("sweep.toml", "sweep.set.pf.feature_particles", "is outside [1, 100000]")
def sweep_set_value_out_of_range(tmp, net, run):
    path = _sweep(tmp, net)
    path.write_text(path.read_text() + '\n[sweep.set]\n"pf.feature_particles" = 1000000000000\n')
    return ["sweep", str(path), "--out", str(tmp / "o"), "--quiet", "--workers", "1"], None


@case("--workers", "must be >= 1")
def sweep_no_workers(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net)), "--out", str(tmp / "o"), "--workers", "0"], None


def _started_sweep(tmp: Path, net: Path) -> tuple[Path, Path]:
    """A sweep on a copy of the net whose first run finished before it was killed (its folder as the
    sweep leaves it; the run's files are not read by the check)."""
    from couplers.errors import recording_reads
    from couplers.publish import mark
    from experiments.sweep.run import INPUTS_FILE, _inputs_text, expand_runs, load_sweep, resolved_spec_toml, \
        sweep_inputs

    mine = _net_copy(tmp, net)
    _config(tmp, mine)
    path = tmp / "sweep.toml"
    path.write_text(SWEEP.format(seeds="[1, 2]"))
    spec = load_sweep(path)
    with recording_reads() as configs:
        base, runs = expand_runs(spec)
    out = tmp / "o"
    (out / "runs" / runs[0].run_id).mkdir(parents=True)
    mark(out, "sweep")
    (out / "sweep.toml").write_text(resolved_spec_toml(spec, base, len(runs)))
    (out / INPUTS_FILE).write_text(_inputs_text(sweep_inputs(spec, runs, configs)))
    (out / "runs" / runs[0].run_id / "summary.json").write_text("{}\n")
    return path, mine


@case("net/zones.geojson", "changed since the sweep", "seed=1", "--force")
def sweep_resumed_onto_a_changed_net(tmp, net, run):
    path, mine = _started_sweep(tmp, net)
    zones = mine / "zones.geojson"
    zones.write_text(zones.read_text().replace('"sigma_p": 3.0', '"sigma_p": 30.0'))
    return ["sweep", str(path), "--out", str(tmp / "o"), "--quiet", "--workers", "1"], None


@case("net/cross.nod.xml", "was removed since the sweep", "--force")
def sweep_resumed_onto_a_net_without_a_file(tmp, net, run):
    path, mine = _started_sweep(tmp, net)
    (mine / "cross.nod.xml").unlink()  # netconvert's input, not read by a run: still a file of the net folder
    return ["sweep", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "changed since the sweep", "--force")
def sweep_resumed_onto_a_changed_config(tmp, net, run):
    path, mine = _started_sweep(tmp, net)
    cfg = tmp / "cfg.toml"
    cfg.write_text(cfg.read_text() + "\n[motion]\nsigma_along = 0.6\n")
    return ["sweep", str(path), "--out", str(tmp / "o"), "--quiet"], None


# ----------------------------------------------------------------------------- coloc net import


@case("notes.txt", "is a file")
def net_import_out_file_force(tmp, net, run):
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--name", "x", "--out", str(_file(tmp)),
            "--experiments-dir", str(tmp / "exps"), "--force"], None


@case("mywork", "already exists", "--force")
def net_import_out_exists(tmp, net, run):
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--name", "x", "--out", str(_user_folder(tmp)),
            "--experiments-dir", str(tmp / "exps")], None


@case("/proc/coloc-corpus", "--out", "cannot be created")
def net_import_out_unwritable(tmp, net, run):
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--name", "x", "--out", "/proc/coloc-corpus/x",
            "--experiments-dir", str(tmp / "exps"), "--no-calibrate"], None


@case("--seed", "2147483647")
def net_import_seed_too_large(tmp, net, run):
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--name", "x", "--out", str(tmp / "x"),
            "--experiments-dir", str(tmp / "exps"), "--seed", str(2**31)], None


@case("x_tlr.toml", "already exists", "--force")
def net_import_config_exists(tmp, net, run):
    (tmp / "exps").mkdir()
    (tmp / "exps" / "x_tlr.toml").write_text("# mine\n")
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--name", "x", "--out", str(tmp / "x"),
            "--experiments-dir", str(tmp / "exps")], None


@case("cross", "is a folder, not a file")
def net_import_net_is_a_folder(tmp, net, run):
    return ["net", "import", "--net", str(net), "--name", "x", "--out", str(tmp / "x"),
            "--experiments-dir", str(tmp / "exps")], None


@case("bs.net.xml", "tlLogic", "cycle 1006 s", "never green", "--rebuild-signals", "--keep-signals")
def net_import_degenerate_signal_programs(tmp, net, run):
    return ["net", "import", "--net", str(SUMO_GAMES / "bs3d" / "bs.net.xml"), "--name", "bs",
            "--out", str(tmp / "bs"), "--experiments-dir", str(tmp / "exps"), "--no-calibrate"], None


@case("--max-feature-distance", "nan m is outside [0, 10000] m")
def net_check_max_feature_distance_nan(tmp, net, run):
    return ["net", "check", str(net), "--max-feature-distance", "nan"], None


@case("--demand[1]", "inf veh/h is outside")
def net_import_demand_infinite(tmp, net, run):
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--name", "x", "--out", str(tmp / "x"),
            "--experiments-dir", str(tmp / "exps"), "--demand", "100", "inf"], None


@case("--zone-cell", "1e-09 m is outside [10, 100000] m")
def net_import_zone_cell_tiny(tmp, net, run):
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--name", "x", "--out", str(tmp / "x"),
            "--experiments-dir", str(tmp / "exps"), "--zone-cell", "1e-9"], None


@case("--workers", "100000 is outside [1, 1024]")
def sweep_workers_huge(tmp, net, run):
    return ["sweep", str(_sweep(tmp, net)), "--out", str(tmp / "o"), "--workers", "100000", "--dry-run"], None
@case("unsorted.rou.xml", "depart", "not sorted by departure", "'early'", "--sort-routes")
def net_import_routes_not_sorted(tmp, net, run):
    (tmp / "unsorted.rou.xml").write_text(UNSORTED)
    return ["net", "import", "--net", str(net / "tlr.net.xml"), "--routes", str(tmp / "unsorted.rou.xml"),
            "--name", "x", "--out", str(tmp / "x"), "--experiments-dir", str(tmp / "exps")], None


@case("cfg.toml", "fusion.rule", "split_ci")
def run_fusion_unknown_rule(tmp, net, run):
    cfg = _config(tmp, net, '[fusion]\nrule = "ci"\n')
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "fusion.feature_ci", "true or false")
def run_fusion_feature_ci_not_bool(tmp, net, run):
    cfg = _config(tmp, net, "[fusion]\nfeature_ci = 1\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "fusion.map_drift", "true or false")
def run_fusion_map_drift_not_bool(tmp, net, run):
    cfg = _config(tmp, net, '[fusion]\nmap_drift = "yes"\n')
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "fusion.belief_max_exclusions", "non-negative integer")
def run_fusion_belief_max_exclusions_negative(tmp, net, run):
    cfg = _config(tmp, net, "[fusion]\nbelief_max_exclusions = -3\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "fusion.belief_innovation_gate", "[0, 1)")
def run_fusion_belief_gate_one(tmp, net, run):
    cfg = _config(tmp, net, "[fusion]\nbelief_innovation_gate = 1.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.gate_on", "'calibrated', 'report'")
def run_gnss_model_gate_on_unknown(tmp, net, run):
    cfg = _config(tmp, net, '[gnss_model]\ngate_on = "raw"\n')
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.velocity_inflation", "'noise', 'innovation'")
def run_gnss_model_velocity_inflation_unknown(tmp, net, run):
    cfg = _config(tmp, net, '[gnss_model]\nvelocity_inflation = "state"\n')
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.bias_share", "[0, 1)")
def run_gnss_model_bias_share_one(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nbias_share = 1.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.bias_tau_s", "positive")
def run_gnss_model_zero_tau(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nbias_tau_s = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.adaptive_window_s", ">= 0")
def run_gnss_model_negative_adaptive_window(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nadaptive_window_s = -3.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.degraded_above_m", ">= 0")
def run_gnss_model_negative_degraded_threshold(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\ndegraded_above_m = -2.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.degraded_velocity_scale", "positive")
def run_gnss_model_zero_velocity_scale(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\ndegraded_above_m = 2.0\ndegraded_velocity_scale = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.bias_follows_report", "true or false")
def run_gnss_model_follow_not_bool(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nbias_follows_report = \"yes\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.innovation_gate", "[0, 1)")
def run_gnss_model_gate_above_one(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\ninnovation_gate = 1.5\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.bias_model", "one of")
def run_gnss_model_unknown_bias_model(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nbias_model = \"double\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.common_update", "one of")
def run_gnss_model_unknown_common_update(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\ncommon_update = \"kalman\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.local_length_m", "positive")
def run_gnss_model_zero_local_length(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nbias_model = \"two_state\"\nlocal_length_m = 0.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.common_share", "[0, 1)")
def run_gnss_model_common_share_one(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\ncommon_share = 1.0\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model", "must be below 1")
def run_gnss_model_shares_above_one(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nbias_model = \"two_state\"\ncommon_share = 0.6\nlocal_share = 0.5\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.bias_tau_s", "number")
def run_gnss_model_text_value(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nbias_tau_s = 'a minute'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "gnss_model.model", "unknown key")
def run_gnss_model_unknown_key(tmp, net, run):
    cfg = _config(tmp, net, "[gnss_model]\nmodel = 'gauss_markov'\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "analysis.warmup_start", "unknown value", "traffic")
def run_warmup_start_unknown(tmp, net, run):
    cfg = _config(tmp, net, "[analysis]\nwarmup_s = 10.0\nwarmup_start = \"saved_state\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "oracle.gnss_channel", "unknown value", "receiver")
def run_joint_oracle_channel_unknown(tmp, net, run):
    cfg = _config(tmp, net, "[oracle]\ngnss_channel = \"pseudoranges\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "oracle.gnss_channel", "satellites")
def run_joint_oracle_fix_channel_without_satellites(tmp, net, run):
    cfg = _config(tmp, net, "[oracle]\ngnss_channel = \"fix\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "oracle.gnss_channel", "expected")
def run_joint_oracle_channel_not_a_string(tmp, net, run):
    cfg = _config(tmp, net, "[oracle]\ngnss_channel = 3\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("cfg.toml", "analysis.warmup_s", "leaves nothing to sense")
def run_warmup_start_traffic_whole_run(tmp, net, run):
    cfg = _config(tmp, net, "[analysis]\nwarmup_s = 30.0\nwarmup_start = \"traffic\"\n")
    return ["run", str(cfg), "--out", str(tmp / "o"), "--quiet"], None


@case("sr.toml", "analysis.warmup_start", "SUMO scenario")
def run_warmup_start_traffic_controlled_scenario(tmp, net, run):
    text = (PROJECT / "experiments" / "single_road.toml").read_text()
    path = tmp / "sr.toml"
    path.write_text(text + "\n[analysis]\nwarmup_s = 5.0\nwarmup_start = \"traffic\"\n")
    return ["run", str(path), "--out", str(tmp / "o"), "--quiet"], None


@case("sweep.toml", "sweep.factors.mm[0].relative.lc.visibility.times", "finite number")
def sweep_relative_negative_times(tmp, net, run):
    _config(tmp, net)
    path = tmp / "sweep.toml"
    path.write_text(SWEEP.format(seeds="[1, 2]")
                    + '[sweep.factors]\nmm = [{label = "a", relative = {"lc.visibility" = {times = -0.5}}}]\n')
    return ["sweep", str(path), "--out", str(tmp / "o"), "--dry-run"], None


@case("sweep.toml", "sweep.factors.mm[0].relative.lc.visibility.of", "unknown parameter")
def sweep_relative_unknown_world_key(tmp, net, run):
    _config(tmp, net)
    path = tmp / "sweep.toml"
    path.write_text(SWEEP.format(seeds="[1, 2]")
                    + '[sweep.factors]\nmm = [{label = "a", relative = {"lc.visibility" = {of = "lc.nope", '
                      'times = 0.5}}}]\n')
    return ["sweep", str(path), "--out", str(tmp / "o"), "--dry-run"], None


@case("sweep.toml", "sweep.design", "no tabulated fraction")
def sweep_fractional_design_too_few_factors(tmp, net, run):
    _config(tmp, net)
    path = tmp / "sweep.toml"
    path.write_text(SWEEP.format(seeds="[1, 2]").replace('methods = ["gnss"]', 'methods = ["gnss"]\ndesign = "fractional"')
                    + '[sweep.factors]\n'
                    + "".join(f'{n} = [{{label = "a", preset = true}}, {{label = "b", set = {{"lc.{k}" = 0.9}}}}]\n'
                              for n, k in (("f1", "eta_threshold"), ("f2", "visibility"), ("f3", "own_consistency_gate"))))
    return ["sweep", str(path), "--out", str(tmp / "o"), "--dry-run"], None


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input(name, tmp_path, cross_net, run_dir, capsys, monkeypatch):
    fn, needles = CASES[name]
    work = tmp_path / "work"
    work.mkdir()
    argv, cwd = fn(work, cross_net, run_dir)
    monkeypatch.chdir(cwd or work)
    before = snapshot(work)
    capsys.readouterr()
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("coloc: error: "), err
    for needle in needles:
        assert needle in err, (needle, err)
    assert snapshot(work) == before  # nothing the case owned was changed, nothing half-written was left


def test_corpus_size():
    """The corpus only grows: a case removed by mistake shows here."""
    assert len(CASES) >= 200


# ----------------------------------------------------------------------------- what --out may replace


def test_run_replaces_an_earlier_run_and_force_adopts_a_folder_without_manifest(cross_net, tmp_path, run_dir):
    """An earlier run (its manifest lists its files) is replaced without --force; a folder without a
    manifest (e.g. written before manifests existed) only with --force, its files kept aside."""
    cfg = _config(tmp_path, cross_net)
    earlier = _run_copy(tmp_path, run_dir)
    assert main(["run", str(cfg), "--out", str(earlier), "--quiet", "--seed", "2"]) == 0
    assert json.loads((earlier / "summary.json").read_text())["seed"] == 2
    assert json.loads((earlier / MARKER).read_text())["kind"] == "run"
    old = (earlier / "summary.json").read_bytes()
    (earlier / MARKER).unlink()
    assert main(["run", str(cfg), "--out", str(earlier), "--quiet", "--seed", "3", "--force"]) == 0
    assert json.loads((earlier / "summary.json").read_text())["seed"] == 3
    assert (earlier / "summary.json.before-coloc").read_bytes() == old
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_force_writes_into_a_user_folder_without_deleting_but_an_empty_folder_needs_no_force(cross_net, tmp_path):
    cfg = _config(tmp_path, cross_net)
    mine = _user_folder(tmp_path)
    assert main(["run", str(cfg), "--out", str(mine), "--quiet", "--force"]) == 0
    assert (mine / "thesis.tex").read_text() == "chapter 1\n" and (mine / "sub" / "data.csv").is_file()
    assert (mine / "summary.json").is_file()
    (tmp_path / "empty").mkdir()
    assert main(["run", str(cfg), "--out", str(tmp_path / "empty"), "--quiet"]) == 0


def test_stale_partial_folders_of_dead_processes_are_removed(cross_net, tmp_path):
    cfg = _config(tmp_path, cross_net)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (tmp_path / f".out.partial-{dead.pid}").mkdir()
    (tmp_path / f".out.partial-{dead.pid}" / "estimates.parquet").write_text("half")
    alive = tmp_path / f".out.partial-{os.getppid()}"  # a live process's: left alone
    alive.mkdir()
    assert main(["run", str(cfg), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert not (tmp_path / f".out.partial-{dead.pid}").exists() and alive.is_dir()


def test_an_output_hidden_by_a_kill_between_the_renames_is_put_back(cross_net, tmp_path, run_dir):
    """SIGKILL after ``out -> .out.old-PID`` and before ``.partial -> out``: the next run restores the
    earlier output and then replaces it as usual."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    shutil.copytree(run_dir, tmp_path / f".out.old-{dead.pid}")
    shutil.copytree(run_dir, tmp_path / f".out.partial-{dead.pid}")
    from couplers.publish import remove_stale

    assert remove_stale(tmp_path, "out") == [tmp_path / f".out.partial-{dead.pid}"]
    assert (tmp_path / "out" / "estimates.parquet").read_bytes() == (run_dir / "estimates.parquet").read_bytes()
    assert main(["run", str(_config(tmp_path, cross_net)), "--out", str(tmp_path / "out"), "--quiet",
                 "--seed", "5"]) == 0
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["seed"] == 5


def test_sigterm_cleans_up_and_exits_143(cross_net, tmp_path, run_dir):
    cfg = _config(tmp_path, cross_net)
    out = _run_copy(tmp_path, run_dir)
    before = snapshot(out)
    proc = subprocess.Popen([sys.executable, "-m", "experiments.cli", "run", str(cfg), "--out", str(out),
                             "--duration", "3600", "--quiet"], cwd=PROJECT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    partial = tmp_path / f".{out.name}.partial-{proc.pid}"
    deadline = time.monotonic() + 60
    while not partial.exists() and time.monotonic() < deadline:
        assert proc.poll() is None
        time.sleep(0.05)
    time.sleep(1.0)  # SUMO is stepping
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert err.strip().splitlines() == ["coloc: terminated; nothing was written"]
    assert not partial.exists() and snapshot(out) == before


def test_sigterm_raised_inside_a_c_callback_still_ends_in_one_line(monkeypatch, tmp_path, capsys):
    """A SIGTERM that lands while numba unpickles a cached kernel's constants (a C callback) reaches Python as a
    SystemError caused by Terminated: still one line and exit 143, no traceback."""
    import experiments.cli as cli

    def stopped_in_callback(args):
        try:
            raise cli.Terminated()
        except cli.Terminated as exc:
            raise SystemError("<function _numba_unpickle> returned a result with an exception set") from exc

    monkeypatch.setattr(cli, "cmd_run", stopped_in_callback)
    assert cli.main(["run", str(tmp_path / "x.toml"), "--out", str(tmp_path / "out")]) == 143
    assert capsys.readouterr().err.strip().splitlines() == ["coloc: terminated; nothing was written"]
    assert cli._stop_in_chain(SystemError("unrelated")) is None


def test_rebuilt_signal_programs_are_plausible(tmp_path, capsys):
    """--rebuild-signals: netconvert's static programs replace the game net's 1000 s phases."""
    from couplers.net.importer.geometry import implausible_signal_programs

    net = SUMO_GAMES / "bs3d" / "bs.net.xml"
    assert len(implausible_signal_programs(net)) == 4
    rc = main(["net", "import", "--net", str(net), "--name", "bs", "--out", str(tmp_path / "bs"),
               "--experiments-dir", str(tmp_path / "exps"), "--no-calibrate", "--rebuild-signals"])
    assert rc == 0, capsys.readouterr().err
    assert implausible_signal_programs(tmp_path / "bs" / "tlr.net.xml") == []
    assert 'signals = "rebuild"' in (tmp_path / "bs" / "scenario.toml").read_text()
    assert implausible_signal_programs(PROJECT / "sumo_nets" / "arterial" / "tlr.net.xml") == []


def test_sigterm_in_a_forked_worker_ends_it_quietly():
    """A pool's workers are forked with the command's SIGTERM handler and ended with SIGTERM: they must die
    as by default (no Terminated traceback), while the command itself still turns SIGTERM into exit 143."""
    code = (
        "import multiprocessing as mp, os, signal, sys, time\n"
        "import experiments.cli as cli\n"
        "cli._MAIN_PID = os.getpid()\n"
        "signal.signal(signal.SIGTERM, cli._on_sigterm)\n"
        "ctx = mp.get_context('fork')\n"
        "p = ctx.Process(target=time.sleep, args=(30,))\n"
        "p.start(); time.sleep(0.5); p.terminate(); p.join(10)\n"
        "print(p.exitcode)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], cwd=PROJECT, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == str(-signal.SIGTERM) and "Terminated" not in res.stderr
