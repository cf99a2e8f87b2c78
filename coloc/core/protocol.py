"""The estimator protocol: one call per frame."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from coloc.core.frame import Frame, StepEstimate


@runtime_checkable
class Estimator(Protocol):
    """``step`` consumes one frame and returns estimates in ``frame.vehicle_ids`` order.

    Vehicles may appear and disappear between frames; a vehicle with
    ``frame.entered`` set starts from the frame's fast-start prior.
    An estimator must never read ``frame.truth``.
    """

    name: str

    def step(self, frame: Frame) -> StepEstimate: ...
