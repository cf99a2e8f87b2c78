"""`coloc net import` / `coloc net check` through the command line, and the generated configs run."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path

import pytest

from experiments.cli import main
from experiments.config import load_config
from osmfixture import write_osm_grid

PROJECT = Path(__file__).resolve().parents[2]


def _import(tmp_path: Path, *extra: str) -> tuple[int, Path, Path]:
    osm = write_osm_grid(tmp_path / "grid.osm")
    out, exps = tmp_path / "nets" / "grid", tmp_path / "exps"
    rc = main(["net", "import", "--osm", str(osm), "--name", "grid", "--out", str(out),
               "--experiments-dir", str(exps), "--seed", "2", "--calibration-s", "600", *extra])
    return rc, out, exps


def test_import_writes_folder_and_both_configs(tmp_path, capsys):
    rc, out, exps = _import(tmp_path)
    assert rc == 0
    text = capsys.readouterr().out
    assert "features:" in text and "demand:" in text and "zones: from building density" in text
    for control, tls_off in (("tlr", False), ("vsr", True)):
        cfg = load_config(exps / f"grid_{control}.toml")
        assert cfg.run.name == f"grid_{control}"
        assert cfg.scenario.control == control
        assert Path(cfg.scenario.net_dir) == out.resolve()
        scen = tomllib.loads((out / "scenario.toml").read_text())
        assert scen["controls"][control]["tls_off"] is tls_off
        assert cfg.report.track_figure_areas == (scen["derived"]["track_area"],)
        # everything else is the arterial's Sec. VI set-up
        art = load_config(PROJECT / "experiments" / f"arterial_{control}.toml")
        assert (cfg.sensors, cfg.motion, cfg.icp, cfg.lc) == (art.sensors, art.motion, art.icp, art.lc)
        # the realistic counterpart: the arterial's realistic preset on this net
        real = load_config(exps / f"grid_{control}_realistic.toml")
        art = load_config(PROJECT / "experiments" / f"arterial_{control}_realistic.toml")
        assert (real.run.name, Path(real.scenario.net_dir), real.report.track_areas) == (
            f"grid_{control}_realistic", out.resolve(), cfg.report.track_areas)
        # but [lc] visibility: measured on this net's own traffic (the grid has buildings: they stay on)
        text_real = (exps / f"grid_{control}_realistic.toml").read_text()
        vis = tomllib.loads(text_real)["lc"]["visibility"]
        assert "measured by `coloc net import` on this net's own" in text_real and 0.05 <= vis <= 1.0
        assert real.perception.occlusion_buildings and "occlusion_buildings" not in text_real
        # and [gnss_error]: a building of the synthetic OSM has no height, which the preset's satellite
        # receiver refuses, so the overlay takes the field model and says why
        assert "have no height" in text_real and tomllib.loads(text_real)["gnss_error"]["model"] == "field"
        assert (real.perception, real.gnss_error, real.inertial, real.lc) == (
            art.perception, dataclasses.replace(art.gnss_error, model="field"), art.inertial,
            dataclasses.replace(art.lc, visibility=vis))
    assert main(["net", "check", str(out)]) == 0
    assert "ok (" in capsys.readouterr().out
    # a second import without --force refuses and changes nothing
    before = {p.name: p.read_bytes() for p in exps.iterdir()}
    rc, _, _ = _import(tmp_path)
    assert rc == 2
    assert "--force" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in exps.iterdir()} == before


def test_realistic_configs_of_a_net_without_buildings(tmp_path, capsys, cross_net):
    """A .net.xml holds no buildings: the realistic overlays turn building occlusion off (the presets'
    true is refused on such a folder) and, with --occlusion-s 0, say that visibility is the arterial's."""
    exps = tmp_path / "exps"
    assert main(["net", "import", "--net", str(cross_net / "tlr.net.xml"), "--name", "x", "--out",
                 str(tmp_path / "x"), "--experiments-dir", str(exps), "--occlusion-s", "0"]) == 0
    for control in ("tlr", "vsr"):
        text = (exps / f"x_{control}_realistic.toml").read_text()
        assert "occlusion_buildings = false" in text and "not derived (imported with --occlusion-s 0)" in text
        real = load_config(exps / f"x_{control}_realistic.toml")
        art = load_config(PROJECT / "experiments" / f"arterial_{control}_realistic.toml")
        assert not real.perception.occlusion_buildings and real.lc == art.lc
        assert "occlusion" not in (exps / f"x_{control}.toml").read_text()  # the idealised ones: untouched


def test_visibility_from_the_occluded_share():
    """As the arterial presets: 42 % occluded -> 0.6 (TLR), 13 % -> 0.85 (VSR)."""
    from experiments.occlusion import visibility_of

    assert [visibility_of(s) for s in (0.42, 0.399, 0.13, 0.134, 0.0, 1.0)] == [0.6, 0.6, 0.85, 0.85, 1.0, 0.05]


def _zones(crs: str | None, x0: float, y0: float, x1: float, y1: float) -> str:
    doc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"zone": "B", "sigma_p": 8.0, "sigma_v": 0.17},
         "geometry": {"type": "Polygon", "coordinates": [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]}}]}
    if crs is not None:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    return json.dumps(doc)


# zones GeoJSON of the --zones cases: (document, words the message must hold)
ZONES_CASES = {
    # a projected CRS: not converted, the accepted ones are listed
    "unknown_crs": (_zones("EPSG:3857", 854000, 5630000, 855000, 5631000),
                    ["'EPSG:3857' is not supported", "urn:ogc:def:crs:OGC:1.3:CRS84", "EPSG:4326",
                     "urn:ogc:def:crs:EPSG::4326", "urn:coloc:sumo-net-xy"]),
    # net x/y metres without the crs marker are read as lon/lat (RFC 7946): implausible, the marker is shown
    "not_lonlat": (_zones(None, 0, 0, 800, 700),
                   ["features[0].geometry.coordinates", "[800, 0] is not a lon/lat",
                    '"crs": {"type": "name", "properties": {"name": "urn:coloc:sumo-net-xy"}}']),
    # lon/lat for a net without geo-reference (the arterial is built from plain XML nodes/edges)
    "no_georef": (_zones("urn:ogc:def:crs:EPSG::4326", 7.67, 45.06, 7.70, 45.08),
                  ["crs", "has no geo-reference", 'projParameter="!"', "urn:coloc:sumo-net-xy"]),
}


@pytest.mark.parametrize("case", ["non_xml", "no_roads", *ZONES_CASES])
def test_bad_input_one_message_exit_2_nothing_written(tmp_path, capsys, case):
    osm = write_osm_grid(tmp_path / "grid.osm", roads=case != "no_roads")
    source = ["--net", str(PROJECT / "sumo_nets" / "arterial" / "tlr.net.xml")] if case == "no_georef" \
        else ["--osm", str(osm)]
    args = ["net", "import", *source, "--name", "bad", "--out", str(tmp_path / "nets" / "bad"),
            "--experiments-dir", str(tmp_path / "exps")]
    if case == "non_xml":
        osm.write_bytes(b"PK\x03\x04 a zip file, not OSM")
    words: list[str] = []
    if case in ZONES_CASES:
        z = tmp_path / "zones.geojson"
        text, words = ZONES_CASES[case]
        z.write_text(text)
        args += ["--zones", str(z)]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("coloc: error: ")
    named = str(tmp_path / "zones.geojson") if case in ZONES_CASES else str(osm)
    assert named in err[0]
    assert all(w in err[0] for w in words), err[0]
    assert not (tmp_path / "nets").exists()  # not even the empty parent folders
    assert not (tmp_path / "exps").exists()


def test_check_exit_status(tmp_path, capsys):
    assert main(["net", "check", str(PROJECT / "sumo_nets" / "arterial")]) == 0
    capsys.readouterr()
    assert main(["net", "check", str(tmp_path / "nowhere")]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "not found" in out[0]


@pytest.mark.slow
def test_generated_configs_run_with_gnss_and_icp_da_lc(tmp_path, capsys):
    """Import the OSM grid, run TLR and VSR for 120 s with gnss and icp_da_lc: reports come out."""
    rc, out, exps = _import(tmp_path)
    assert rc == 0
    for control in ("tlr", "vsr"):
        res = tmp_path / "results" / control
        assert main(["run", str(exps / f"grid_{control}.toml"), "--out", str(res), "--duration", "120",
                     "--methods", "gnss,icp_da_lc", "--quiet"]) == 0
        summary = json.loads((res / "summary.json").read_text())
        assert set(summary["methods"]) == {"gnss", "icp_da_lc"}
        assert summary["traffic"]["mean_vehicles"] > 5
        assert summary["traffic"]["teleports"] == 0
        assert (res / "report.html").is_file()
        for block in summary["methods"].values():
            assert 0 < block["rmse_pos_m"] < 15
