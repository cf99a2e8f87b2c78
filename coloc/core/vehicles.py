"""Vehicle-state bookkeeping shared by estimators: vehicles come and go between frames."""

from __future__ import annotations

import numpy as np


def match_ids(previous_ids: np.ndarray, current_ids: np.ndarray) -> np.ndarray:
    """Row of each current id in ``previous_ids``, -1 where it was not there (vectorised)."""
    current = np.asarray(current_ids)
    previous = np.asarray(previous_ids)
    if previous.size == 0 or current.size == 0:
        return np.full(current.shape[0], -1, dtype=np.int64)
    order = np.argsort(previous, kind="stable")
    sorted_prev = previous[order]
    pos = np.searchsorted(sorted_prev, current)
    pos_clipped = np.minimum(pos, sorted_prev.size - 1)
    found = sorted_prev[pos_clipped] == current
    return np.where(found, order[pos_clipped], -1).astype(np.int64)


def carry_states(
    previous_ids: np.ndarray,
    previous_mean: np.ndarray,
    previous_cov: np.ndarray,
    current_ids: np.ndarray,
    entered: np.ndarray,
    prior_z: np.ndarray,
    prior_R: np.ndarray,
    idx: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Posterior of the last step in the current order; new or re-entered vehicles from the prior.

    Returns (mean (N,4), cov (N,4,4), fresh (N,) bool). Fresh vehicles start from
    the fast-start prior (Brambilla Sec. VI-A) and are not predicted this step.
    ``idx``: ``match_ids(previous_ids, current_ids)`` if the caller already has it.
    """
    if idx is None:
        idx = match_ids(previous_ids, current_ids)
    fresh = (idx < 0) | np.asarray(entered, dtype=bool)
    n = len(current_ids)
    mean = np.empty((n, 4))
    cov = np.empty((n, 4, 4))
    keep = ~fresh
    mean[keep] = previous_mean[idx[keep]]
    cov[keep] = previous_cov[idx[keep]]
    if fresh.any():
        if not np.all(np.isfinite(prior_z[fresh])):
            raise ValueError("frame marks a vehicle as new but carries no fast-start prior for it")
        mean[fresh] = prior_z[fresh]
        cov[fresh] = prior_R[fresh]
    return mean, cov, fresh
