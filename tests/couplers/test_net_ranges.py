"""Numbers of a net folder's files in their physical ranges (couplers/net/ranges.py), as `coloc net check` and the
loader see them: one problem line naming the file and field, no shapely warning before it."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import pytest

from couplers.net import ranges
from couplers.errors import InputError
from couplers.net.check import check_net_folder
from couplers.net.folder import load_net_folder

PROJECT = Path(__file__).resolve().parents[2]


def _copy(tmp_path: Path, net: Path, name: str, old: str, new: str) -> Path:
    dst = tmp_path / "net"
    shutil.copytree(net, dst)
    f = dst / name
    text = f.read_text()
    assert old in text
    f.write_text(text.replace(old, new, 1))
    return dst


CASES = [
    ("zones.geojson", '"sigma_p": 3.0', '"sigma_p": Infinity', "features[0].properties.sigma_p: inf m is outside"),
    ("zones.geojson", '"sigma_p": 3.0', '"sigma_p": 1e308', "features[0].properties.sigma_p: 1e+308 m is outside"),
    ("zones.geojson", '"sigma_v": 0.1', '"sigma_v": 1e9', "features[0].properties.sigma_v: 1e+09 m/s is outside"),
    ("zones.geojson", "[0, -500], [0, 500]", "[0, -500], [NaN, 500]", "features[0].geometry: coordinate nan m"),
    ("zones.geojson", "[0, -500], [0, 500]", "[0, -500], [1e300, 500]", "features[0].geometry: coordinate 1e+300 m"),
    ("zones.geojson", "[0, -500], [0, 500]", "[0, -500], [0, 5000000]", "features[0].geometry: a vertex at"),
    ("areas.geojson", "]]]", ", [NaN, 0]]]]", "features[0].geometry"),
    ("features.add.xml", 'x="-350.0"', 'x="nan"', "poi[0].x/y: coordinate nan m is not finite"),
    ("features.add.xml", 'y="12.0"', 'y="inf"', "poi[0].x/y: coordinate inf m is not finite"),
    ("features.add.xml", 'x="-350.0"', 'x="-3500000.0"', "poi[0].x/y: poi 'f0' at x=-3.5e+06"),
    ("demand.rou.xml", 'begin="0"', 'begin="nan"', "demand.rou.xml: flow[0].begin: nan s is outside"),
    ("demand.rou.xml", 'period="6"', 'period="-inf"', "demand.rou.xml: flow[0].period: -inf s is outside"),
    ("demand.rou.xml", 'maxSpeed="15"', 'maxSpeed="1e9"', "demand.rou.xml: vType[0].maxSpeed: 1e9 m/s is outside"),
    ("scenario.toml", "[controls]", "[sumo]\nend = inf\n[controls]", "scenario.toml: sumo.end: expected a finite number"),
]


@pytest.mark.parametrize("name,old,new,words", CASES)
def test_net_check_names_the_file_and_field_and_warns_nothing(tmp_path, cross_net, name, old, new, words):
    folder = _copy(tmp_path, cross_net, name, old, new)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a shapely RuntimeWarning would fail here
        problems, _ = check_net_folder(folder)
        with pytest.raises(InputError) as exc:
            load_net_folder(folder)
    assert len(problems) == 1 and words in problems[0], problems
    assert problems[0].startswith(str(folder / ("demand.rou.xml" if name == "demand.rou.xml" else name)))
    assert exc.value.describe() == problems[0]


def test_sumo_words_and_times_are_left_to_sumo(tmp_path, cross_net):
    folder = _copy(tmp_path, cross_net, "demand.rou.xml", "</routes>",
                   '<vehicle id="v" route="we" depart="1:00:00" departPos="random" departSpeed="max"/>'
                   '<flow id="g" route="we" begin="0" end="60" period="exp(0.1)"/></routes>')
    assert load_net_folder(folder).routes.is_file()


def test_shipped_net_folders_are_inside_the_ranges():
    for d in sorted((PROJECT / "sumo_nets").iterdir()):
        if (d / "scenario.toml").is_file():
            load_net_folder(d)


def test_net_boundary_is_the_nets_conv_boundary(cross_net):
    assert ranges.net_boundary(cross_net / "tlr.net.xml") == (-400.0, -400.0, 400.0, 400.0)
