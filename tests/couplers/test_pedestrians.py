"""SUMO pedestrians as moving features (couplers.sensing.pedestrians, [features] pedestrians) on sumo_nets/arterial_ped."""

from dataclasses import replace
from pathlib import Path

import libsumo
import numpy as np
import pytest

from couplers.errors import InputError
from couplers.net.folder import load_net_folder
from couplers.sensing.pedestrians import CLASS_PEDESTRIAN, CLASS_STATIC, FeatureRegistry, FeaturesParams, PersonStates
from couplers.sensing.perception import PerceptionParams
from couplers.sensing.sensors import SensorParams
from couplers.sumo_coupler import SumoCoupler, SumoScenario

ROOT = Path(__file__).resolve().parents[2]
PED_NET = ROOT / "sumo_nets" / "arterial_ped"
ON = FeaturesParams(pedestrians=True)


def _scenario(duration=90.0, net=PED_NET):
    return SumoScenario(net=load_net_folder(net), control="tlr", seed=1, duration_s=duration)


def test_person_features_match_libsumo_and_ids_are_stable():
    rows_of: dict[str, int] = {}
    k0 = None
    checked = 0
    with SumoCoupler(_scenario(), SensorParams(features=ON)) as c:
        for fr in c.frames():
            t = fr.truth
            k0 = int((t.feature_class == CLASS_STATIC).sum()) if k0 is None else k0
            assert (t.feature_class[:k0] == CLASS_STATIC).all() and (t.feature_class[k0:] == CLASS_PEDESTRIAN).all()
            ids = set(libsumo.person.getIDList())
            for row in range(k0, len(t.feature_ids)):
                pid = t.feature_ids[row]
                assert rows_of.setdefault(pid, row) == row  # a person keeps its row for the run
                if pid not in ids:  # gone: NaN, never measured again
                    assert np.isnan(t.features_true[row]).all()
                    assert not (fr.truth.v2f_feature == row).any()
                    continue
                px, py = libsumo.person.getPosition(pid)
                speed = libsumo.person.getSpeed(pid)
                ang = np.radians(libsumo.person.getAngle(pid))
                np.testing.assert_allclose(t.features_true[row], [px, py, speed * np.sin(ang), speed * np.cos(ang)],
                                           atol=1e-9)
                checked += 1
            assert ids <= set(t.feature_ids[k0:])
            # class label of every row: its feature's class
            np.testing.assert_array_equal(fr.v2f_class, t.feature_class[t.v2f_feature])
            # idealised V2F: every feature within Rs, pedestrians included (model (4))
            d = np.hypot(*(t.features_true[t.v2f_feature, :2] - t.x_true[fr.v2f_owner, :2]).T)
            assert (d <= 50.0 + 1e-9).all()
    assert checked > 500 and len(rows_of) > 20
    assert (fr.v2f_class == CLASS_PEDESTRIAN).any()


def test_perception_rows_carry_classes_and_clutter_is_static():
    sensors = SensorParams(features=ON, perception=PerceptionParams())
    n_clutter = n_ped = 0
    with SumoCoupler(_scenario(45.0), sensors) as c:
        for fr in c.frames():
            feat = fr.truth.v2f_feature
            clutter = feat < 0
            assert (fr.v2f_class[clutter] == CLASS_STATIC).all()
            np.testing.assert_array_equal(fr.v2f_class[~clutter], fr.truth.feature_class[feat[~clutter]])
            np.testing.assert_array_equal(c.last_detections.klass, fr.v2f_class)
            n_clutter += int(clutter.sum())
            n_ped += int((fr.v2f_class == CLASS_PEDESTRIAN).sum())
    assert n_clutter > 0 and n_ped > 0


def test_pedestrians_off_frames_carry_no_classes():
    with SumoCoupler(_scenario(15.0), SensorParams()) as c:
        for fr in c.frames():
            assert fr.v2f_class is None and fr.truth.feature_class is None
            assert fr.truth.features_true.shape[0] == 64


def test_net_without_persons_is_refused():
    with pytest.raises(InputError, match="files.persons"):
        SumoCoupler(_scenario(15.0, ROOT / "sumo_nets" / "arterial"), SensorParams(features=ON))


def test_registry_rows():
    reg = FeatureRegistry(np.array(["a", "b"], dtype=object), np.zeros((2, 4)))
    p = lambda ids, x: PersonStates(np.array(ids, dtype=object), np.array(x, float).reshape(-1, 2),  # noqa: E731
                                    np.ones((len(ids), 2)))
    np.testing.assert_array_equal(reg.update(p(["p1", "p0"], [[1, 1], [2, 2]])), [2, 3])
    np.testing.assert_array_equal(reg.update(p(["p0", "p2"], [[3, 3], [4, 4]])), [3, 4])
    assert list(reg.ids) == ["a", "b", "p1", "p0", "p2"]
    assert np.isnan(reg.states[2]).all() and reg.states[3, 0] == 3 and reg.states[4, 1] == 4
    np.testing.assert_array_equal(reg.klass, [0, 0, 1, 1, 1])
