"""The cooperative belief's own fault exclusion ([fusion] belief_innovation_gate, belief_max_exclusions;
coloc.methods.coop_fusion): absent, the belief gates as the own-sensor track does, byte for byte; set, the
belief rides out a longer run of reflected fixes while the own track (and so the `gnss` benchmark) takes the
fix after its own max_exclusions, and nothing else of the state changes."""

from dataclasses import replace

import numpy as np
import pytest

from coloc.inference.params import IcpParams
from coloc.methods.coop_fusion import CoopFusion, FusionParams
from coloc.methods.icp_known_da import IcpKnownDA
from test_coop_two_state import TRUE_MOTION, TWO, two_state_frames

GATED = replace(TWO, innovation_gate=0.999, max_exclusions=3)


def _reflected(frames, vehicle, start, length, offset_m=60.0):
    """The frames with ``vehicle``'s fix moved ``offset_m`` east for ``length`` steps from ``start`` (a run of
    reflected fixes; the report unchanged, as a receiver that does not see it)."""
    out = []
    for k, f in enumerate(frames):
        if start <= k < start + length:
            z = np.array(f.gnss_z, dtype=float, copy=True)
            z[vehicle, 0] += offset_m
            f = replace(f, gnss_z=z)
        out.append(f)
    return out


def _run(fusion_params, frames):
    est = IcpKnownDA(IcpParams(motion=TRUE_MOTION), fusion=CoopFusion(fusion_params, GATED))
    states = []
    for f in frames:
        est.step_with_association(f, f.truth.v2f_feature)
        states.append(est.state.split)
    return states


def test_defaults_are_the_receiver_model_itself():
    fusion = CoopFusion(FusionParams(), GATED)
    assert fusion.belief_model is GATED
    b = CoopFusion(FusionParams(belief_innovation_gate=0.99, belief_max_exclusions=8), GATED).belief_model
    assert (b.innovation_gate, b.max_exclusions) == (0.99, 8)
    assert replace(b, innovation_gate=GATED.innovation_gate, max_exclusions=GATED.max_exclusions) == GATED


def test_the_belief_rides_out_a_longer_run_and_the_own_track_does_not_change():
    frames = _reflected(two_state_frames(4, steps=16), vehicle=1, start=4, length=8)
    base = _run(FusionParams(), frames)
    longer = _run(FusionParams(belief_max_exclusions=20), frames)
    own_streak = [int(s.own_streak[1]) for s in base]
    belief_base = [int(s.streak[1]) for s in base]
    belief_long = [int(s.streak[1]) for s in longer]
    # the own track and, by default, the belief: three fixes excluded, the fourth taken, and so on
    assert max(own_streak) == 3 and max(belief_base) == 3
    # the belief given a longer run excludes the whole run of 8 and takes the first good fix after it
    assert belief_long[4:12] == list(range(1, 9)) and belief_long[12] == 0
    for a, b in zip(base, longer):
        np.testing.assert_array_equal(a.own_mean, b.own_mean)
        np.testing.assert_array_equal(a.own_cov, b.own_cov)
    # the belief did not follow the reflected fixes: it is nearer the truth at the run's end
    truth = frames[11].truth.x_true[1, :2]
    assert np.hypot(*(longer[11].mean[1, :2] - truth)) < np.hypot(*(base[11].mean[1, :2] - truth))


def test_set_to_the_models_values_is_byte_identical():
    frames = _reflected(two_state_frames(5, steps=10), vehicle=0, start=3, length=5)
    base = _run(FusionParams(), frames)
    same = _run(FusionParams(belief_innovation_gate=GATED.innovation_gate,
                             belief_max_exclusions=GATED.max_exclusions), frames)
    for a, b in zip(base, same):
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.cov, b.cov)


@pytest.mark.parametrize("key,value", [("belief_innovation_gate", 1.0), ("belief_innovation_gate", -0.5),
                                       ("belief_max_exclusions", -2), ("belief_max_exclusions", 2.5)])
def test_bad_values_are_refused(key, value):
    with pytest.raises(ValueError):
        FusionParams(**{key: value})
