"""ICP-DA-PF's BPA-L stopped per connected component (``[pf] bpa_stop = "component"``): on a graph whose
components are independent, each component ends exactly as if it ran alone under the net rule."""

import numpy as np
import pytest
import scipy.sparse as sp

from coloc.inference.params import IcpParams
from coloc.inference.row_consensus import consensus_graph
from coloc.methods.icp_da_pf import PfParams, bpa_components, pf_bpa_localization, pf_step_comm

J = 300
R1 = np.diag([0.04, 0.04, 0.01, 0.01])
PARAMS = IcpParams(bpa_max_iterations=12, stop_pos_m=1e-3, stop_vel_mps=1e-3, consensus_iterations=3)


def _scene():
    """Component A: vehicles 0, 1, 2 and tracks 0, 1 (vehicle 0 sees both, a loop through the
    vehicles); component B: vehicles 3, 4 and tracks 2, 3 (a loop as well, settling at another
    iteration).
    Every vehicle is a V2V neighbour of every other, yet no track is shared across A and B."""
    g = np.random.default_rng(11)
    v_mean = np.array([[0.0, 0.0, 10.0, 0.0], [6.0, 1.0, 10.0, 0.0], [12.0, -1.0, 10.0, 0.0],
                       [80.0, 0.0, 8.0, 0.0], [86.0, 0.0, 8.0, 0.0]])
    f_mean = np.array([[20.0, 5.0, 0.0, 0.0], [10.0, -6.0, 0.0, 0.0], [95.0, 4.0, 0.0, 0.0],
                       [90.0, -5.0, 0.0, 0.0]])
    vp = np.stack([g.multivariate_normal(m, np.diag([4.0, 4.0, 0.04, 0.04]), J) for m in v_mean])
    fp = np.stack([g.multivariate_normal(m, np.diag([9.0, 9.0, 0.01, 0.01]), J) for m in f_mean])
    out = vp + g.normal(scale=0.3, size=vp.shape)  # the carried set of the "latest_message" recursion
    entry_vehicle = np.array([0, 0, 1, 2, 2, 3, 3, 4, 4])
    entry_track = np.array([0, 1, 0, 0, 1, 2, 3, 2, 3])
    truth_v = v_mean + g.normal(scale=[1.5, 1.5, 0.1, 0.1], size=v_mean.shape)
    z = f_mean[entry_track] - truth_v[entry_vehicle] + g.normal(scale=[0.2, 0.2, 0.1, 0.1], size=(9, 4))
    logc0 = np.log(np.array([0.05, 0.1, 0.02, 0.05, 0.1, 0.03, 0.04, 0.02, 0.06]))
    return vp, fp, out, entry_vehicle, entry_track, z, logc0


def _run(vehicles, tracks, pf, params=PARAMS):
    """BPA-L on the sub-problem of ``vehicles`` and ``tracks`` (renumbered, order kept)."""
    vp, fp, out, ev, et, z, logc0 = _scene()
    sel = np.flatnonzero(np.isin(ev, vehicles) & np.isin(et, tracks))
    ev_s, et_s = np.searchsorted(vehicles, ev[sel]), np.searchsorted(tracks, et[sel])
    n = len(vehicles)
    adj = sp.csr_matrix(~np.eye(n, dtype=bool))
    g = np.random.default_rng(5)
    log_b0 = -0.5 * g.random((5, J))[vehicles]  # fixed per vehicle, whatever the sub-problem
    return pf_bpa_localization(
        vp[vehicles], log_b0, fp[tracks], np.zeros((len(tracks), J)), ev_s, et_s, logc0[sel],
        np.arange(sel.size), sel, np.zeros(sel.size), z, np.array([R1] * 9), adj, params, pf,
        out[vehicles], log_b0 - 0.1, workspace=None,
    ), sel


@pytest.mark.parametrize("kernel", ["tree", "fast"])
def test_stopping_per_component_equals_each_component_alone(kernel):
    pf = PfParams(seed=1, kernel=kernel, bpa_stop="component")
    whole, _ = _run(np.arange(5), np.arange(4), pf)
    a, sel_a = _run(np.arange(3), np.arange(2), PfParams(seed=1, kernel=kernel))
    b, sel_b = _run(np.arange(3, 5), np.arange(2, 4), PfParams(seed=1, kernel=kernel))
    assert a.iterations != b.iterations  # the components settle at different iterations
    assert whole.iterations == max(a.iterations, b.iterations) and whole.converged
    for part, sel, vehicles in ((a, sel_a, np.arange(3)), (b, sel_b, np.arange(3, 5))):
        np.testing.assert_array_equal(whole.vehicle_logw[vehicles], part.vehicle_logw)
        np.testing.assert_array_equal(whole.entry_feature_logw[sel], part.entry_feature_logw)
        np.testing.assert_array_equal(whole.entry_message_logw[sel], part.entry_message_logw)
        np.testing.assert_array_equal(whole.first_feature_logw[sel], part.first_feature_logw)
        np.testing.assert_array_equal(whole.first_message_logw[sel], part.first_message_logw)
        np.testing.assert_array_equal(whole.entry_iterations[sel], part.iterations)
    # The net rule keeps the settled component iterating: its result moves (within the tolerance).
    net, _ = _run(np.arange(5), np.arange(4), PfParams(seed=1, kernel=kernel))
    assert net.iterations == whole.iterations
    fast_one = sel_a if a.iterations < b.iterations else sel_b
    assert not np.array_equal(net.entry_feature_logw[fast_one], whole.entry_feature_logw[fast_one])
    assert whole.pair_evaluations <= net.pair_evaluations


def test_one_component_is_the_net_rule_bit_for_bit():
    vehicles, tracks = np.arange(3), np.arange(2)
    comp, _ = _run(vehicles, tracks, PfParams(seed=1, kernel="fast", bpa_stop="component"))
    net, _ = _run(vehicles, tracks, PfParams(seed=1, kernel="fast"))
    assert comp.iterations == net.iterations
    for f in ("vehicle_logw", "entry_feature_logw", "entry_message_logw", "first_feature_logw"):
        np.testing.assert_array_equal(getattr(comp, f), getattr(net, f))


def test_components_and_their_communication():
    _, _, _, ev, et, _, _ = _scene()
    adj = sp.csr_matrix(~np.eye(6, dtype=bool))  # vehicle 5 has no entry
    graph = consensus_graph(ev, et, adj)
    comp_e, comp_v, count = bpa_components(graph, ev, 6)
    assert count == 3
    assert len(set(comp_e[:5])) == 1 and len(set(comp_e[5:])) == 1 and comp_e[0] != comp_e[5]
    np.testing.assert_array_equal(comp_v[:5], comp_e[[0, 2, 3, 5, 7]])
    assert comp_v[5] not in comp_e
    # Communication: each component's vehicles broadcast for their own iterations.
    its = np.where(comp_e == comp_e[0], 4, 2)
    per = pf_step_comm(ev, et, adj, np.empty(0, np.int64), its, 6, PARAMS, PfParams())
    a = pf_step_comm(ev, et, adj, np.empty(0, np.int64), 4, 6, PARAMS, PfParams())
    b = pf_step_comm(ev, et, adj, np.empty(0, np.int64), 2, 6, PARAMS, PfParams())
    np.testing.assert_array_equal(per.bytes[:3], a.bytes[:3])
    np.testing.assert_array_equal(per.bytes[3:], b.bytes[3:])
    assert per.rounds == a.rounds


def test_bad_bpa_stop_is_refused():
    with pytest.raises(ValueError, match="bpa_stop"):
        PfParams(bpa_stop="track")
