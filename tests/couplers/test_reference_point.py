"""[scenario] reference_point: the vehicle's centre instead of SUMO's front bumper.

With "front_bumper" (the default) the frames are SUMO's positions (tests/couplers/test_sumo_coupler.py checks
them against libsumo) and the paper configs' estimates are byte-identical (tools/estimate_hashes.py --quick
against the main checkout)."""

import sys
from pathlib import Path

import libsumo
import numpy as np
import pytest

from couplers.net.folder import load_net_folder
from couplers.sensing.perception import PerceptionParams
from couplers.sensing.sensors import SensorParams
from couplers.sumo_coupler import SumoCoupler, SumoScenario, _front_bumpers
from couplers.traffic.reference_point import centre_from_front
from couplers.traffic.sumo import SumoTraffic

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from world_residual import SHARP_TURN_RAD, residuals  # noqa: E402


def test_centre_of_a_straight_vehicle_is_half_its_length_behind():
    front = np.array([[10.0, 5.0], [0.0, 0.0]])
    direction = np.array([[1.0, 0.0], [0.0, -1.0]])  # east, south
    np.testing.assert_allclose(centre_from_front(front, direction, np.array([2.25, 6.0])), [[7.75, 5.0], [0.0, 6.0]])


def test_centre_of_a_turning_vehicle_is_the_chord_midpoint():
    """Both bumpers on a circle of radius R (SUMO's angle: the chord from the rear to the front bumper): the
    centre is the chord's midpoint, L/2 from the front bumper and sqrt(R^2 - L^2/4) from the circle's centre."""
    big_r, length = 8.0, 4.5
    half_angle = np.arcsin(0.5 * length / big_r)  # each bumper half the chord from its midpoint
    phi = np.linspace(0.0, 2 * np.pi, 7)  # the chord midpoint's polar angle
    front = big_r * np.stack([np.cos(phi + half_angle), np.sin(phi + half_angle)], axis=1)
    rear = big_r * np.stack([np.cos(phi - half_angle), np.sin(phi - half_angle)], axis=1)
    direction = (front - rear) / length
    centre = centre_from_front(front, direction, np.full(phi.size, 0.5 * length))
    np.testing.assert_allclose(centre, 0.5 * (front + rear), atol=1e-12)
    np.testing.assert_allclose(np.hypot(*(front - centre).T), 0.5 * length)
    np.testing.assert_allclose(np.hypot(*centre.T), np.sqrt(big_r**2 - 0.25 * length**2))


def test_centre_states_against_sumo(cross_net):
    """Every vehicle's centre is its SUMO position minus half its SUMO length along its angle; the front
    bumper comes back exactly for the footprints; velocity, heading and acceleration are SUMO's either way."""
    sc = SumoScenario(net=load_net_folder(cross_net), control="tlr", seed=3, duration_s=60.0, reference_point="centre")
    checked = 0
    with SumoTraffic(sc.sumo_options(), "centre") as traffic:
        while not traffic.done():
            s = traffic.step()
            for i, v in enumerate(s.ids):
                px, py = libsumo.vehicle.getPosition(v)
                half = 0.5 * libsumo.vehicle.getLength(v)
                ang = np.radians(libsumo.vehicle.getAngle(v))
                u = np.array([np.sin(ang), np.cos(ang)])
                np.testing.assert_allclose(s.xy[i], np.array([px, py]) - half * u, atol=1e-9)
                assert s.front_offset[i] == half
                np.testing.assert_allclose(s.velocity[i], libsumo.vehicle.getSpeed(v) * u, atol=1e-9)
                checked += 1
            np.testing.assert_allclose(_front_bumpers(s), [libsumo.vehicle.getPosition(v) for v in s.ids], atol=1e-9)
    assert checked > 200


def test_footprints_are_not_moved_twice(cross_net):
    """The occlusion footprints and the road-user targets sit where they sit with "front_bumper": the same
    vehicles and states, seen from the other reference point."""
    perception = PerceptionParams(occlusion_vehicles=True, road_users=True)
    sensors = SensorParams(perception=perception)
    out = {}
    for ref in ("front_bumper", "centre"):
        sc = SumoScenario(net=load_net_folder(cross_net), control="tlr", seed=3, duration_s=45.0, reference_point=ref)
        c = SumoCoupler(sc, sensors)
        seen, step = [], c.traffic.step
        c.traffic.step = lambda: seen.append(step()) or seen[-1]  # the last road states of the run
        with c:
            for _ in c.frames():
                pass
        road = seen[-1]
        out[ref] = (road, _front_bumpers(road), c._dims)
    (a, fa, da), (b, fb, db) = out["front_bumper"], out["centre"]
    assert a.ids.size > 5 and (a.ids == b.ids).all()
    np.testing.assert_allclose(fb, fa, atol=1e-9)
    np.testing.assert_allclose(b.xy, fa - 0.5 * db[:, :1] * a.direction, atol=1e-9)


@pytest.mark.slow
def test_centre_explains_the_turns(cross_net):
    """Displacement minus the trapezoid of the reported velocities: at sharp-turn steps the front bumper
    slides by about L/2 x the heading change, the centre does not (arterial seed 101, 300 s: 1.26 m vs
    0.18 m RMS; docs/validation/consistency.md "Kinematics of the world")."""
    rms = {}
    for ref in ("front_bumper", "centre"):
        r, h = residuals(str(cross_net), "tlr", 3, 240.0, ref)
        sharp = h > SHARP_TURN_RAD
        assert sharp.sum() >= 5
        rms[ref] = (np.sqrt(np.mean(r**2)), np.sqrt(np.mean(r[sharp] ** 2)))
    assert rms["front_bumper"][1] > 0.5
    assert rms["centre"][1] < 0.4 * rms["front_bumper"][1]
    assert rms["centre"][0] < rms["front_bumper"][0]
