"""The V2X channel of one frame (``Frame.v2x``): what estimators need to exchange messages over lossy,
asymmetric V2V links within a budget of broadcast rounds (docs/architecture.md "The frame
contract").

The coupler (``couplers/sensing/v2x.py``, the ``[v2x]`` config table) decides the channel; this module only
carries it and realises it, so that every estimator sees the *same* packets arrive in the same round
and no estimator seeds anything itself.

* Links are the entries of the frame's ``neighbors`` CSR matrix, in its storage order (rows sorted,
  columns sorted within a row). Entry ``k`` in row ``i`` and column ``j`` is the *directed* link
  j -> i: "i hears j's broadcast". Both directions of every V2V pair are entries, each with its own
  losses. :func:`directed_links` gives ``(src, dst)`` per entry, the convention of
  :mod:`coloc.inference.lossy_consensus`.
* ``delivery_prob[k]``: probability that one broadcast of ``src[k]`` reaches ``dst[k]`` (packet
  delivery ratio at the link's distance, through buildings or not).
* ``rounds_per_step``: broadcast rounds that fit in the step (0 = unlimited). Every iterative
  exchange of a method draws rounds from this one budget.
* ``seed``: the step's channel seed. Round ``r`` (0-based, counted over the whole step, across
  every exchange of a method) is realised by :func:`round_deliveries` from
  ``SeedSequence([seed, r])``: independent across rounds and links, the same for every estimator.

An estimator running on a frame with ``v2x`` set must pass a message on link ``k`` in round ``r``
only when ``round_deliveries(frame.v2x, r)[k]`` is True, and must stop exchanging after
``rounds_per_step`` rounds (when it is not 0). With ``v2x`` None every link delivers every round, as
the paper assumes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

#: ``rounds_per_step`` value meaning "as many rounds as the method wants".
UNLIMITED_ROUNDS = 0


@dataclass(frozen=True)
class V2xFrame:
    """The channel of one step, aligned with the frame's ``neighbors`` (see the module docstring)."""

    delivery_prob: np.ndarray  # (E,) float in [0, 1], one per CSR entry of neighbors (j -> i)
    rounds_per_step: int  # 0 = unlimited
    seed: int  # the step's channel seed, >= 0

    def __post_init__(self):
        p = np.asarray(self.delivery_prob)
        if p.ndim != 1:
            raise ValueError(f"delivery_prob must be 1-D (one per neighbors entry), got shape {p.shape}")
        if p.size and not (np.all(p >= 0.0) and np.all(p <= 1.0)):
            raise ValueError("delivery_prob must lie in [0, 1]")
        if isinstance(self.rounds_per_step, bool) or int(self.rounds_per_step) != self.rounds_per_step \
                or self.rounds_per_step < 0:
            raise ValueError(f"rounds_per_step must be an integer >= 0, got {self.rounds_per_step!r}")
        if int(self.seed) != self.seed or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")

    @property
    def n_links(self) -> int:
        return int(self.delivery_prob.shape[0])

    @property
    def unlimited(self) -> bool:
        return self.rounds_per_step == UNLIMITED_ROUNDS

    def rounds_available(self, wanted: int) -> int:
        """How many of ``wanted`` rounds fit in the step's budget."""
        return int(wanted) if self.unlimited else min(int(wanted), int(self.rounds_per_step))


def directed_links(neighbors: sp.csr_matrix) -> tuple[np.ndarray, np.ndarray]:
    """(src (E,), dst (E,)) of every CSR entry of ``neighbors``: entry (row i, column j) is j -> i."""
    n = neighbors.shape[0]
    dst = np.repeat(np.arange(n, dtype=np.int64), np.diff(neighbors.indptr))
    return neighbors.indices.astype(np.int64), dst


def round_deliveries(v2x: V2xFrame, round_index: int) -> np.ndarray:
    """(E,) bool: which links deliver their packet in round ``round_index`` of the step.

    Drawn from ``SeedSequence([v2x.seed, round_index])``, one uniform per link: the same realisation
    for every caller, independent across rounds, directions and links."""
    if isinstance(round_index, bool) or int(round_index) != round_index or round_index < 0:
        raise ValueError(f"round_index must be an integer >= 0, got {round_index!r}")
    rng = np.random.default_rng(np.random.SeedSequence([int(v2x.seed), int(round_index)]))
    return rng.random(v2x.n_links) < v2x.delivery_prob


def deliveries(v2x: V2xFrame, first_round: int, n_rounds: int) -> np.ndarray:
    """(R, E) bool: rounds ``first_round`` .. ``first_round + n_rounds - 1`` stacked (for
    :func:`coloc.inference.lossy_consensus.running_sum_consensus`)."""
    out = np.empty((int(n_rounds), v2x.n_links), dtype=bool)
    for k in range(int(n_rounds)):
        out[k] = round_deliveries(v2x, first_round + k)
    return out
