"""Communication accounting: the V2V messages and bytes a method sends per vehicle
and step, from what its code actually exchanges.

Every number on the air is counted as one 8-byte word (:data:`WORD_BYTES`): floats, and also the
integers that say what a value is about (a feature or track id, a consensus degree). Headers of the
radio and the network (MAC, security, CAM/CPM framing) are not counted. A *message* is one
broadcast: a vehicle sends one per round, carrying its values for all its features at once, so one
broadcast round serves every feature's consensus of that round.

Message formats (words per feature, i.e. per V2F row or (vehicle, track) entry in a consensus):

* Gaussian ICP (``icp_known_da``, ``icp_da_lc``), every consensus round of every BPA-L iteration,
  :data:`GAUSSIAN_CONSENSUS_WORDS` = 16: the feature id, the 10 upper-triangle entries of the
  message's Lambda and the 4 of its eta (eq. (20) averages m_{i->k} in information form), and one
  more word: lossless (Metropolis weights 1 / (1 + max(d_i, d_j))) the sender's degree in that
  feature's consensus graph, which the receiver needs for the weight; lossy (running-sum ratio
  consensus, :mod:`coloc.inference.lossy_consensus`) the running sum of the weight z (the 14 values
  are then the running sums sigma of y).
* ICP-DA-PF (``icp_da_pf``, ``icp_known_da_pf``), every BPA-L iteration: ``consensus_iterations``
  rounds of average consensus of the Jf log-weights of m_{i->k} (28), each feature
  1 + 1 + Jf words (id, degree, log-weights), then max(``consensus_iterations``, 1) rounds of max
  consensus (29), 1 + Jf words (id, values): :func:`pf_words`.
* New tracks (``icp_da_lc``, ``icp_da_pf``): a vehicle with rows that start a track broadcasts them
  once in the step, so that rows of several vehicles implying one feature start one track (the
  lowest id wins). LC: the id, the implied position (2) and its 2x2 covariance (3), the inputs of
  :func:`coloc.methods.icp_da_lc.birth_clusters`, :data:`LC_BIRTH_WORDS` = 6; PF: the id, the 4-D
  mean and the 10 upper-triangle covariance entries of the Gaussian its particles are drawn from
  (every holder draws the same particles from the synchronized generators),
  :data:`PF_BIRTH_WORDS` = 15.

A feature row takes part in a consensus only when another vehicle observing the same feature is its
V2V neighbour (intended graph): a vehicle with no such row has nobody to talk to and sends nothing.

Not counted (the paper's idealisations, shared by all methods alike): the vehicles' beacons (CAMs)
that tell who is a neighbour and which features a neighbour observes, and the flooding that tells a
vehicle the participant count |V_k ∩ C| of (20) (computed directly, :mod:`coloc.inference`); the feature tracks each
vehicle holds between steps (the track store of :mod:`coloc.inference.feature_store` and the track
merges are computed as if every vehicle held the same copy); the GNSS-only benchmark sends nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: bytes of one word on the air (a float64, or an id / degree sent as one word).
WORD_BYTES = 8
#: words per feature per consensus round of the Gaussian BPA-L (id + 10 + 4 + degree or running z).
GAUSSIAN_CONSENSUS_WORDS = 1 + 10 + 4 + 1
#: words per new-track announcement of ICP-DA-LC (id, implied position, its 2x2 covariance).
LC_BIRTH_WORDS = 1 + 2 + 3
#: words per new-track announcement of ICP-DA-PF (id, 4-D mean, 10 covariance entries).
PF_BIRTH_WORDS = 1 + 4 + 10


def pf_words(feature_particles: int) -> tuple[int, int]:
    """Words per feature in one round of the PF's average consensus (id, degree, Jf log-weights) and
    of its max consensus (id, Jf values)."""
    return 2 + int(feature_particles), 1 + int(feature_particles)


@dataclass(frozen=True)
class CommCount:
    """What the vehicles of one step sent: ``messages`` (N,) broadcasts and ``bytes`` (N,) per vehicle
    (frame order), ``rounds`` the consensus rounds the step used (all exchanges of the method)."""

    messages: np.ndarray
    bytes: np.ndarray
    rounds: int = 0

    @staticmethod
    def zeros(n: int) -> "CommCount":
        return CommCount(np.zeros(int(n), dtype=np.int64), np.zeros(int(n), dtype=np.int64), 0)

    def __add__(self, other: "CommCount") -> "CommCount":
        return CommCount(self.messages + other.messages, self.bytes + other.bytes, self.rounds + other.rounds)


def broadcast_rounds(owner: np.ndarray, active: np.ndarray, n_vehicles: int, rounds: int, words_per_row: int) -> CommCount:
    """``rounds`` broadcast rounds in which every vehicle owning at least one ``active`` row sends one
    message of ``words_per_row`` words per active row it owns (``owner`` (O,) vehicle of each row)."""
    per_vehicle = np.bincount(np.asarray(owner, dtype=np.int64)[np.asarray(active, dtype=bool)],
                              minlength=int(n_vehicles)).astype(np.int64)
    rounds = int(rounds)
    messages = (per_vehicle > 0).astype(np.int64) * rounds
    return CommCount(messages, per_vehicle * (rounds * int(words_per_row) * WORD_BYTES), rounds)


def announcements(owner: np.ndarray, n_vehicles: int, words_per_row: int) -> CommCount:
    """One message from every vehicle owning at least one of the rows ``owner`` (O,), with
    ``words_per_row`` words per row (e.g. the new tracks it starts). Uses no consensus round."""
    out = broadcast_rounds(owner, np.ones(np.asarray(owner).size, dtype=bool), n_vehicles, 1, words_per_row)
    return CommCount(out.messages, out.bytes, 0)
