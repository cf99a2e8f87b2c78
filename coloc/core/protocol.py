"""The estimator protocols: one call per frame.

An estimator is built by its method's entry in :mod:`coloc.methods.registry`, which also says
which protocol it is driven through: :class:`Estimator` (measurements only) or, for the
known-association bounds, :class:`KnownAssociationEstimator` (the runner adds the true
association of every V2F row). An object may implement both (ICP-DA-PF: ``icp_da_pf`` and
``icp_known_da_pf``); the registry's ``known_association`` flag decides which call is made.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from coloc.core.frame import Frame, StepEstimate


@runtime_checkable
class Estimator(Protocol):
    """``step`` consumes one frame and returns estimates in ``frame.vehicle_ids`` order.

    Vehicles may appear and disappear between frames; a vehicle with
    ``frame.entered`` set starts from the frame's fast-start prior. The entry protocol: where
    ``frame.prior_has_fix`` says that prior is this step's receiver fix (``start = "gnss_fix"``), the
    fix is not applied to it again (:func:`coloc.core.vehicles.entry_fix_rows` names those rows,
    :func:`coloc.core.vehicles.keep_entry_fix` undoes a batch update on them).
    An estimator must never read ``frame.truth``.
    """

    name: str

    def step(self, frame: Frame) -> StepEstimate: ...


@runtime_checkable
class KnownAssociationEstimator(Protocol):
    """A bound told the true association: ``step_with_association(frame, v2f_feature)`` with
    ``v2f_feature`` (O,) the stable integer feature id of every V2F row of ``frame`` (-1: a row
    to leave out, e.g. clutter), taken by the caller from the truth (the runner from
    ``frame.truth.v2f_feature``), never by the estimator. Otherwise as :class:`Estimator`:
    rows in ``frame.vehicle_ids`` order, vehicles come and go, ``frame.truth`` is not read.
    """

    name: str

    def step_with_association(self, frame: Frame, v2f_feature: np.ndarray) -> StepEstimate: ...
