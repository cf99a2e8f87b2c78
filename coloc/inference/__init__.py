"""Inference shared by the estimators: the Gaussian ICP machinery (Brambilla et al. Secs. III,
IV-B, IV-D), data association BP, consensus, particle utilities and the topology
pseudo-measurement.

Modules: :mod:`~coloc.inference.params` (:class:`IcpParams`), :mod:`~coloc.inference.gaussian`
(information algebra), :mod:`~coloc.inference.row_consensus` (the consensus graph on V2F rows),
:mod:`~coloc.inference.feature_store` (feature tracks), :mod:`~coloc.inference.bpa` (the BPA-L
loop), :mod:`~coloc.inference.association` (BPA-DA), :mod:`~coloc.inference.consensus` (average
and max consensus), :mod:`~coloc.inference.particles` (resampling, weighted moments, kernel
density), :mod:`~coloc.inference.particle_bp` (ICP-DA-PF's particle BPA-L and :class:`PfParams`),
:mod:`~coloc.inference.topology` (Zhang's and Gulati's pseudo-measurement). They import
:mod:`coloc.kernels` and :mod:`coloc.core`, never a method.

The Gaussian ICP
----------------

With the association fixed (known, or decided by ICP-DA-LC's MAP rule (30)-(31)),
the V2F likelihood (18) of a row (vehicle i, feature k) is the single Gaussian
p(z_ik | x_Vi, x_Fk) = N(z_ik; x_Fk - x_Vi, R_ik) of model (4), every belief is
Gaussian and the BPA-L of eqs. (19)-(22) is Gaussian message passing, i.e. the
distributed Kalman filter of Soatti et al. [40] ("LC" implementation, Sec. IV-D).
Everything here works in information form (Lambda = P^-1, eta = P^-1 m),
batched over the O V2F rows with numpy (no per-vehicle Python loops).

Mapping of the equations to code (one BPA-L iteration n,
:func:`coloc.inference.bpa.bpa_localization`):

* (11)/(12) prior beliefs b^(0): supplied by the caller (GNSS-updated vehicle
  prediction; predicted feature tracks, uniform -- zero information -- for a
  feature nobody tracked before: :func:`coloc.inference.feature_store.birth_information`).
* (19) vehicle -> feature message. The cavity b_i^(n-1) / m_{k->i}^(n-1) is
  Lambda_i - Lambda_{k->i}; integrating the likelihood over x_Vi gives
  x_Fk ~ N(m_cav + z_ik, P_cav + R_ik)  (:func:`coloc.inference.gaussian.relative_message`,
  offset +z).
* (20) feature belief b_k = b_k^(0) prod_{i in V_k} m_{i->k}: the product is a
  sum of information, computed *by average consensus* among the vehicles that
  sense k, over the V2V links between them
  (:func:`coloc.inference.row_consensus.consensus_graph`): every
  participant holds its own message, the consensus average is multiplied by
  the number of participants of its component |V_k ∩ C| and the prior
  information b_k^(0) (shared track, held by every participant) is added
  locally. Each participant ends with its own copy of b_k; with finitely many
  consensus rounds the copies differ.
* (21) feature -> vehicle message: vehicle i divides its copy of b_k by its own
  message (extrinsic information Lambda_k - Lambda_{i->k}, projected on the PSD cone by
  :func:`coloc.inference.gaussian.psd_clip`) and integrates the
  likelihood over x_Fk: x_Vi ~ N(m_ext - z_ik, P_ext + R_ik).
* (22) vehicle belief b_i = b_i^(0) prod_k m_{k->i}: information sum over the
  vehicle's rows (a sparse (N, O) incidence product; :mod:`coloc.inference.bpa`).

Iterations stop by the rule of Sec. V-A: every vehicle's position mean moved
by less than ``stop_pos_m`` and its velocity by less than ``stop_vel_mps``
(the global "all vehicles" test a max consensus would give), or after
``bpa_max_iterations``.

Across steps a track keeps one message per vehicle
(:class:`coloc.inference.feature_store.FeatureStore`), built on the vehicle's own-sensor belief
(``IcpParams.feature_message``); the step's feature estimate is (20) with BPA-L's final messages
(:func:`coloc.inference.bpa.step_feature_beliefs`).

Consensus design: the per-feature groups are run in *one* consensus on a
graph whose nodes are the V2F rows: rows (i, k) and (j, k) are linked iff
vehicles i and j are V2V neighbours (:func:`coloc.inference.row_consensus.consensus_graph`).
Its Metropolis weights are exactly those of each feature's participant-induced subgraph, so
one numba kernel runs every feature's consensus at once (cost
O(iterations * edges * 14): the 10 distinct entries of a symmetric Lambda and
the 4 of eta). The participant count |V_k ∩ C| is the size of the row's
connected component; a vehicle learns it exactly by flooding participant ids
for diameter-many rounds (a max consensus), which we compute directly.
Graph, weights and counts are built by one numba pass per time step
(:func:`coloc.inference.row_consensus.row_consensus_weights`, equal bit for bit to
``metropolis_weights(consensus_graph(...))`` and
:func:`coloc.inference.row_consensus.row_components`). On a
component that is a complete graph (always the case when Rc >= 2 Rs) the
Metropolis matrix is J/m, a projection, so the consensus stops after its first
round there (:func:`coloc.kernels.icp.complete_component_consensus`).

Lossy links: :mod:`coloc.inference.lossy_consensus` keeps the exact average when packets are lost
asymmetrically (ratio consensus by exchange of running sums, Hadjicostis et al. 2016) and runs max
consensus over the rounds that got through. With a V2X channel in the frame (``frame.v2x``) the
Gaussian BPA-L runs the consensus of (20) that way on the row graph, over the links each round
delivered and within the step's round budget
(:class:`coloc.inference.row_consensus.ChannelRowConsensus`, :mod:`coloc.inference.bpa`); the
particle ICP still assumes every consensus message arrives. What each method sends per step is
counted by :mod:`coloc.inference.comm`.

Consistent fusion (``[fusion]``): :mod:`coloc.inference.split_ci` replaces the BPA-L iterations by one
pass in which vehicles exchange only their own-sensor messages and fuse the feature evidence by split
covariance intersection (the rule, its weights and its sources are there; the vehicle filters in
:mod:`coloc.methods.coop_fusion`).

Clutter: :mod:`coloc.inference.existence` carries an existence probability per feature track (BP
multitarget tracking, Meyer et al. 2018) and updates it from the BPA-DA beliefs (13)-(17) in
log-odds over vehicles; ICP-DA-LC uses it when ``[lc] track_existence`` is set (its step 9).

Performance layout: the BPA-L iterations run as numba passes over the rows
(:mod:`coloc.kernels.icp`; ``coloc.inference.bpa.BPA_KERNELS = False`` selects the batched
numpy reference, equal up to rounding); :class:`~coloc.inference.feature_store.FeatureStore`
caches what it derives from its (immutable) arrays.
"""
