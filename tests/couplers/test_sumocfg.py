"""A researcher's SUMO scenario (.sumocfg) imported and run on its own clock (couplers.net.importer.sumocfg)."""

from __future__ import annotations

import gzip
import json
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from couplers.errors import InputError
from couplers.net.importer.sumocfg import clock, demand_departures, parse_time, read_sumocfg
from couplers.traffic.sumo import SumoOptions, TrafficStats, libsumo
from experiments.cli import main
from sumocfgfixture import A_BEFORE, A_DEPARTS, B_BEFORE, B_DEPARTS, BEGIN, END, build_sumocfg_scenario


@pytest.fixture(scope="module")
def scen(tmp_path_factory) -> Path:
    return build_sumocfg_scenario(tmp_path_factory.mktemp("scen") / "lust_like")


@pytest.fixture(scope="module")
def imported(scen, tmp_path_factory):
    """The scenario imported with --sumocfg: (net folder, experiments folder, printed lines)."""
    base = tmp_path_factory.mktemp("imported")
    out, exps = base / "net", base / "exps"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["net", "import", "--sumocfg", str(scen), "--name", "lust", "--out", str(out),
                   "--experiments-dir", str(exps)])
    assert rc == 0
    return out, exps, buf.getvalue()


# --------------------------------------------------------------------------- reading the configuration


@pytest.mark.parametrize("flat", [False, True])
def test_read_sumocfg_both_layouts(tmp_path, flat):
    cfg = read_sumocfg(build_sumocfg_scenario(tmp_path / "s", flat=flat))
    base = tmp_path / "s"
    assert cfg.net == base / "net" / "cross.net.xml"
    assert cfg.routes == (base / "routes" / "a.rou.xml", base / "routes" / "b.rou.xml.gz")
    assert cfg.additional == (base / "add" / "stops.add.xml",)
    assert (cfg.begin, cfg.end, cfg.step_length) == (BEGIN, END, 0.75)
    assert cfg.ignored == ("time-to-teleport",)


def test_times_and_clock():
    assert parse_time("25200", Path("x"), "begin") == 25200.0
    assert parse_time("07:00:00", Path("x"), "begin") == 25200.0
    assert parse_time("1:07:00:00", Path("x"), "begin") == 86400.0 + 25200.0
    with pytest.raises(InputError, match="not a time"):
        parse_time("seven", Path("x"), "begin")
    assert clock(25200.0) == "07:00" and clock(25230.0) == "07:00:30" and clock(90000.0) == "01:00 +1d"


def test_read_sumocfg_refuses_with_the_option(tmp_path):
    cfg = build_sumocfg_scenario(tmp_path / "s")
    (tmp_path / "s" / "routes" / "b.rou.xml.gz").unlink()
    with pytest.raises(InputError) as err:
        read_sumocfg(cfg)
    assert err.value.field == "route-files" and "b.rou.xml.gz: file not found" in err.value.message
    bad = tmp_path / "bad.sumocfg"
    bad.write_text("<configuration><time><begin value='100'/><end value='50'/></time>"
                   "<input><net-file value='s/net/cross.net.xml'/><route-files value='s/routes/a.rou.xml'/></input>"
                   "</configuration>")
    with pytest.raises(InputError, match="not after begin"):
        read_sumocfg(bad)


def test_departures_before_begin_are_what_sumo_drops(scen):
    """The import's count of departures before the begin is what SUMO itself drops when it runs the
    scenario's own configuration (checked by running it: those vehicles never depart)."""
    cfg = read_sumocfg(scen)
    dep = demand_departures(cfg.routes)
    assert (dep.first, dep.vehicles, dep.flows) == (25000.0, 90, 1)
    assert dep.before(BEGIN) == (A_BEFORE + B_BEFORE, 1) == (35, 1)
    departs = {}
    for path in cfg.routes:
        opener = gzip.open if path.suffix == ".gz" else open
        with opener(path, "rt") as fh:
            for line in fh:
                if "<vehicle " in line:
                    vid = line.split('id="')[1].split('"')[0]
                    departs[vid] = float(line.split('depart="')[1].split('"')[0])
    libsumo.start(["sumo", "-c", str(scen), "--end", repr(BEGIN + 300.0), "--no-step-log", "true",
                   "--no-warnings", "true", "--step-length", "0.75"])
    try:
        assert libsumo.simulation.getTime() == BEGIN
        departed = []
        while libsumo.simulation.getTime() < BEGIN + 300.0:
            libsumo.simulationStep()
            departed += libsumo.simulation.getDepartedIDList()
    finally:
        libsumo.close()
    early = {v for v, d in departs.items() if d < BEGIN}
    assert len(early) == 35
    assert not early & set(departed)  # every vehicle departing before the begin is dropped
    assert {v for v, d in departs.items() if BEGIN <= d <= BEGIN + 250.0} <= set(departed)
    flow = sorted(v for v in departed if v.startswith("fb."))
    assert flow and len(flow) <= 5  # from the begin only: 25200, 25240, ... (< 25400), none of 25100..25160


# --------------------------------------------------------------------------- the import


def test_import_keeps_files_and_clock(scen, imported):
    out, exps, text = imported
    scen_toml = tomllib.loads((out / "scenario.toml").read_text())
    assert scen_toml["sumo"] == {"begin": BEGIN, "step_length": 0.75, "end": END}
    assert scen_toml["files"]["routes"] == ["demand_1.rou.xml", "demand_2.rou.xml.gz"]
    # the route files as given, byte for byte (the gzipped one still gzipped)
    assert (out / "demand_1.rou.xml").read_bytes() == (scen.parent / "routes" / "a.rou.xml").read_bytes()
    assert (out / "demand_2.rou.xml.gz").read_bytes() == (scen.parent / "routes" / "b.rou.xml.gz").read_bytes()
    demand = scen_toml["derived"]["demand"]
    assert demand["before_begin"]["vehicles_trips"] == 35 and demand["before_begin"]["flows"] == 1
    assert "dropped by SUMO" in demand["before_begin"]["handled"]
    assert "35 of 90 vehicles/trips depart before it" in text and "SUMO drops" in text
    assert "begin 25200 s (07:00)" in text
    # the additional file's bus stop is a feature place, its signal program is loaded into every run, its
    # detector is said not to be
    assert scen_toml["derived"]["features"]["bus_stop"] == 1
    assert scen_toml["files"]["additional"] == "signals.add.xml"
    assert scen_toml["derived"]["signal_programs"]["programs"] == ["tlLogic 'C' program 'cfg'"]
    assert 'programID="cfg"' in (out / "signals.add.xml").read_text()
    assert any("1 inductionLoop of stops.add.xml are not loaded" in x for x in scen_toml["not_derived"]["items"])
    from couplers.net.folder import load_net_folder
    from couplers.sumo_coupler import SumoScenario

    folder = load_net_folder(out)
    cmd = SumoScenario(net=folder, control="tlr", seed=1, begin_s=BEGIN, duration_s=60.0).sumo_options().command()
    assert cmd[cmd.index("--additional-files") + 1] == str(out / "signals.add.xml")
    assert cmd[cmd.index("--route-files") + 1].endswith("demand_1.rou.xml," + str(out / "demand_2.rou.xml.gz"))
    for control, program in (("tlr", "cfg"), ("vsr", "off")):  # VSR: every signal off, the scenario's too
        libsumo.start(SumoScenario(net=folder, control=control, seed=1, begin_s=BEGIN, duration_s=60.0)
                      .sumo_options().command())
        try:
            assert libsumo.trafficlight.getProgram("C") == program
        finally:
            libsumo.close()
    assert any("time-to-teleport" in x for x in scen_toml["not_derived"]["items"])
    # the options of the generated demand are not recorded (they were not used)
    assert "demand_veh_per_h" not in scen_toml["import"] and "calibration_s" not in scen_toml["import"]
    from experiments.config import load_config

    for control in ("tlr", "vsr"):
        cfg = load_config(exps / f"lust_{control}.toml")
        assert (cfg.scenario.begin_s, cfg.scenario.step_s, cfg.run.duration_s) == (BEGIN, 0.75, 3600.0)


def test_net_check_says_begin_against_demand(imported, capsys, tmp_path):
    out, _, _ = imported
    assert main(["net", "check", str(out)]) == 0
    line = capsys.readouterr().out
    assert "begin 25200 s (07:00), departures 25000 s (06:56:40) to 25485 s (07:04:45)" in line
    assert "35 of 90 vehicles/trips depart before it" in line
    # a begin after the last departure, and an unknown [sumo] key, are problems
    import shutil

    for name, old, new, want in (("late", "begin = 25200.0", "begin = 28000.0", "after the demand's last departure"),
                                 ("typo", "begin = 25200.0", "begin = 25200.0\nbegn = 1.0", "sumo.begn: unknown key")):
        bad = tmp_path / name
        shutil.copytree(out, bad)
        (bad / "scenario.toml").write_text((bad / "scenario.toml").read_text().replace(old, new))
        assert main(["net", "check", str(bad)]) == 1
        printed = capsys.readouterr().out
        assert want in printed and len(printed.strip().splitlines()) == 1


def _refused(capsys, argv, want: str, tmp_path: Path) -> None:
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and want in err[0], err
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written


def test_refusals_one_line_exit_2_nothing_written(scen, tmp_path, capsys):
    base = scen.parent
    common = ["--name", "x", "--out", str(tmp_path / "net"), "--experiments-dir", str(tmp_path / "exps")]
    net, a, b = base / "net" / "cross.net.xml", base / "routes" / "a.rou.xml", base / "routes" / "b.rou.xml.gz"
    for flag in ("--net", "--osm"):
        _refused(capsys, ["net", "import", flag, str(scen), *common], f"{scen}: {flag}: a SUMO configuration "
                 "(.sumocfg): import it with --sumocfg", tmp_path)
    _refused(capsys, ["net", "import", "--net", str(net), "--routes", str(scen), *common],
             f"{scen}: --routes: a SUMO configuration (.sumocfg): import it with --sumocfg", tmp_path)
    _refused(capsys, ["net", "import", "--net", str(net), "--routes", str(a), "--demand", "100", "200", *common],
             "--demand: not with --routes: it shapes the generated demand", tmp_path)
    _refused(capsys, ["net", "import", "--sumocfg", str(scen), "--duration", "600", *common],
             "--duration: not with --sumocfg: it shapes the generated demand", tmp_path)
    _refused(capsys, ["net", "import", "--sumocfg", str(scen), "--routes", str(a), *common],
             "not with --sumocfg: the configuration names the route and additional files", tmp_path)
    late = tmp_path / "late.sumocfg"
    late.write_text(scen.read_text().replace('value="net/', f'value="{base}/net/')
                    .replace('value="routes/a.rou.xml, routes/b.rou.xml.gz"', f'value="{a},{b}"')
                    .replace('value="add/', f'value="{base}/add/').replace('"25200"', '"27000"'))
    _refused(capsys, ["net", "import", "--sumocfg", str(late), *common],
             "late.sumocfg: begin: 27000 s (07:30) is after the last departure of the demand (25485 s", tmp_path)


def test_routes_take_gz_and_several_files(scen, tmp_path, capsys):
    base = scen.parent
    out = tmp_path / "net"
    rc = main(["net", "import", "--net", str(base / "net" / "cross.net.xml"),
               "--routes", str(base / "routes" / "a.rou.xml"), "--routes", str(base / "routes" / "b.rou.xml.gz"), "--name", "two", "--out", str(out),
               "--experiments-dir", str(tmp_path / "exps")])
    assert rc == 0
    scen_toml = tomllib.loads((out / "scenario.toml").read_text())
    assert scen_toml["files"]["routes"] == ["demand_1.rou.xml", "demand_2.rou.xml.gz"]
    assert "begin" not in scen_toml["sumo"]  # no clock of its own: as before, from 0
    assert main(["net", "check", str(out)]) == 0
    assert "91 vehicles/flows/trips" in capsys.readouterr().out
    out2 = tmp_path / "net2"  # comma-separated, in one option
    assert main(["net", "import", "--net", str(base / "net" / "cross.net.xml"), "--routes",
                 f"{base / 'routes' / 'a.rou.xml'},{base / 'routes' / 'b.rou.xml.gz'}", "--name", "two",
                 "--out", str(out2), "--experiments-dir", str(tmp_path / "exps2")]) == 0
    assert (out2 / "demand_2.rou.xml.gz").read_bytes() == (out / "demand_2.rou.xml.gz").read_bytes()
    # b alone uses a's routes: refused, naming the file and the vehicle
    assert main(["net", "import", "--net", str(base / "net" / "cross.net.xml"), "--routes",
                 str(base / "routes" / "b.rou.xml.gz"), "--name", "b", "--out", str(tmp_path / "net3"),
                 "--experiments-dir", str(tmp_path / "exps3")]) == 2
    assert "b.rou.xml.gz: vehicle 'b0': route 'ew' is not defined" in capsys.readouterr().err
    one = tmp_path / "a.rou.xml.gz"  # one gzipped file
    one.write_bytes(gzip.compress((base / "routes" / "a.rou.xml").read_bytes(), mtime=0))
    out4 = tmp_path / "net4"
    assert main(["net", "import", "--net", str(base / "net" / "cross.net.xml"), "--routes", str(one), "--name", "gz",
                 "--out", str(out4), "--experiments-dir", str(tmp_path / "exps4")]) == 0
    assert tomllib.loads((out4 / "scenario.toml").read_text())["files"]["routes"] == "demand_1.rou.xml.gz"
    assert main(["net", "check", str(out4)]) == 0


# --------------------------------------------------------------------------- the clock of a run


def test_sumo_options_begin_only_when_set():
    opts = SumoOptions(net=Path("n"), routes=Path("r"), seed=1)
    assert "--begin" not in opts.command() and opts.command()[opts.command().index("--end") + 1] == "3600.0"
    cmd = SumoOptions(net=Path("n"), routes=Path("r"), seed=1, begin=25200.0, end=25320.0).command()
    assert cmd[cmd.index("--begin") + 1] == "25200.0" and cmd[cmd.index("--end") + 1] == "25320.0"


def test_traffic_intervals_from_the_begin():
    st = TrafficStats(step_length=1.0, origin=25250.0)
    for k in range(1, 401):
        st.add(25250.0 + k, 2, 0, 0, 10.0, 0)
    st.flush()
    assert [(r["interval_start_s"], r["interval_end_s"]) for r in st.rows] == [(25250.0, 25550.0), (25550.0, 25650.0)]


def test_config_begin_s_validated(imported, tmp_path):
    from experiments.config import config_from_dict

    out, _, _ = imported
    base = {"run": {"name": "r", "methods": ["gnss"]}, "scenario": {"net_dir": str(out)}}
    cfg = config_from_dict(base, tmp_path / "c.toml")
    assert cfg.scenario.begin_s == BEGIN and cfg.run.duration_s == END - BEGIN  # the folder's [sumo]
    for val, want in ((-1.0, "must be >= 0"), (26000.0, "after the last departure of the demand")):
        with pytest.raises(InputError) as err:
            config_from_dict({**base, "scenario": {"net_dir": str(out), "begin_s": val}}, tmp_path / "c.toml")
        assert err.value.field == "scenario.begin_s" and want in err.value.message
    with pytest.raises(InputError, match="only for scenario.kind"):
        config_from_dict({"run": {"name": "r"}, "scenario": {"kind": "single_road", "begin_s": 10.0}}, tmp_path / "c")


def test_shipped_config_keeps_its_clock():
    from experiments.config import load_config

    root = Path(__file__).resolve().parents[2]
    cfg = load_config(root / "experiments" / "arterial_tlr.toml")
    assert (cfg.scenario.begin_s, cfg.scenario.step_s, cfg.run.duration_s) == (0.0, 0.75, 3600.0)
    assert cfg.notes == load_config(root / "experiments" / "arterial_tlr.toml").notes
    assert not any(k.startswith(("scenario.begin_s", "scenario.step_s", "run.duration_s")) for k, _ in cfg.notes)


def test_time_axis_on_the_scenario_clock():
    from matplotlib.figure import Figure

    from experiments.report.figures import _time_axis
    from experiments.report.load import _Run

    ax = Figure().subplots()
    _time_axis(ax, [_Run(run_dir=Path("r"), config={"scenario": {"begin_s": 0.0}}, summary={})])
    assert ax.get_xlabel() == "time [min]"
    ax = Figure().subplots()
    _time_axis(ax, [_Run(run_dir=Path("r"), config={"scenario": {"begin_s": BEGIN}}, summary={})])
    assert "time of day" in ax.get_xlabel()
    assert ax.xaxis.get_major_formatter()(420.0, 0) == "07:00" and ax.xaxis.get_major_formatter()(425.0, 0) == "07:05"


@pytest.mark.slow
def test_run_from_the_begin_matches_sumo(scen, imported, tmp_path):
    """A 240 s gnss run of the imported scenario simulates 07:00-07:04 and sees, step by step, the vehicles
    SUMO has in the net when it runs the researcher's own .sumocfg for the same window."""
    out, exps, _ = imported
    run = tmp_path / "run"
    assert main(["run", str(exps / "lust_tlr.toml"), "--out", str(run), "--duration", "240", "--methods", "gnss",
                 "--quiet"]) == 0
    est = pd.read_parquet(run / "estimates.parquet", columns=["t", "vehicle"])
    traffic = pd.read_parquet(run / "traffic.parquet")
    summary = json.loads((run / "summary.json").read_text())
    # SUMO on the researcher's configuration, with the options coloc runs it with (couplers.traffic.sumo)
    opts = SumoOptions(net=Path("n"), routes=Path("r"), seed=1, begin=BEGIN, end=BEGIN + 240.0)
    extra = opts.command()[opts.command().index("--seed"):]
    libsumo.start(["sumo", "-c", str(scen), *extra])
    counts, ids = [], set()
    try:
        while libsumo.simulation.getTime() < BEGIN + 240.0 - 1e-9:
            libsumo.simulationStep()
            counts.append((libsumo.simulation.getTime(), libsumo.vehicle.getIDCount()))
            ids.update(libsumo.vehicle.getIDList())
    finally:
        libsumo.close()
    sumo = pd.Series({t: n for t, n in counts})
    ours = est.groupby("t").size().reindex(sumo.index, fill_value=0)
    assert ours.index[0] == BEGIN + 0.75  # t is the scenario's clock
    assert est["t"].min() == BEGIN + 0.75 and est["t"].max() == BEGIN + 240.0
    np.testing.assert_array_equal(ours.to_numpy(), sumo.to_numpy())
    assert set(est["vehicle"].unique()) == ids
    early = {f"a{i}" for i, d in enumerate(A_DEPARTS) if d < BEGIN} | {f"b{i}" for i, d in enumerate(B_DEPARTS)
                                                                       if d < BEGIN}
    assert len(early) == 35 and not early & ids  # departing before 07:00: dropped, by SUMO and by the run
    assert traffic["interval_start_s"].iloc[0] == BEGIN
    # the scenario's signal program ran (north-south green 60 s): without it, SUMO gives other counts
    libsumo.start(["sumo", "-n", str(out / "tlr.net.xml"), "-r", f"{out / 'demand_1.rou.xml'},"
                   f"{out / 'demand_2.rou.xml.gz'}", *extra])
    try:
        assert libsumo.trafficlight.getProgram("C") == "0"
        plain = []
        while libsumo.simulation.getTime() < BEGIN + 240.0 - 1e-9:
            libsumo.simulationStep()
            plain.append(libsumo.vehicle.getIDCount())
    finally:
        libsumo.close()
    assert plain != sumo.tolist()
    assert summary["traffic"]["mean_vehicles"] == pytest.approx(sumo.mean(), rel=1e-12)


def test_empty_window_says_where_the_demand_is(imported, tmp_path, capsys):
    """The defect this replaces: a run from 0 of a demand on its own clock said "run longer"."""
    _, exps, _ = imported
    cfg = tmp_path / "from0.toml"
    text = (exps / "lust_tlr.toml").read_text().replace('net_dir = "../net"', f'net_dir = "{exps.parent / "net"}"')
    cfg.write_text(text.replace("begin_s = 25200.0", "begin_s = 0.0"))
    assert main(["run", str(cfg), "--out", str(tmp_path / "run"), "--duration", "30", "--methods", "gnss",
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scenario.begin_s: no vehicle in the simulated window [0, 30] s (00:00-00:00:30)" in err[0]
    assert "the demand departs from 25000 s (06:56:40) on; set [scenario] begin_s = 25200" in err[0]
    assert "run longer" not in err[0] and not (tmp_path / "run").exists()


def test_benches_start_sumo_as_coloc_run(imported):
    """Every bench's SUMO run is `coloc run`'s (experiments.runner.sumo_scenario): every route file, the
    additional files, the begin; the realistic overlays' occlusion is measured from that begin too."""
    from experiments.config import load_config
    from experiments.runner import folder_scenario, sumo_scenario

    out, exps, text = imported
    cfg = load_config(exps / "lust_tlr.toml")
    cmd = sumo_scenario(cfg).sumo_options().command()
    assert cmd == folder_scenario(out, "tlr", cfg.run.seed, cfg.run.duration_s).sumo_options().command()
    assert float(cmd[cmd.index("--begin") + 1]) == BEGIN
    assert cmd[cmd.index("--route-files") + 1].endswith("demand_1.rou.xml," + str(out / "demand_2.rou.xml.gz"))
    assert cmd[cmd.index("--additional-files") + 1] == str(out / "signals.add.xml")
    assert "occlusion (TLR, 600 s from the begin, seed 1)" in text
    real = (exps / "lust_tlr_realistic.toml").read_text()
    assert "600 s simulated from the begin (07:00" in real or "no (vehicle, feature) pair was in view" in real
