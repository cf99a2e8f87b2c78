"""V2F rows the classifier labels as vehicles are not landmarks: the estimators drop them.

With ``[perception] road_users`` a vehicle's sensors report every other car (``Frame.v2f_class`` =
:data:`CLASS_VEHICLE`). A stopped car looks like a landmark for a while and then drives away, and
localizing against it would tie the vehicles' errors to another vehicle's motion. The estimators
(ICP-DA-LC, ICP known DA, ICP-DA-PF) therefore take out every row of class vehicle before the
association (the simplest honest option; tracking them as moving objects is not done). The rows
they see are the frame's other rows, in the frame's order; an estimate's ``v2f_assignment`` is
expanded back to the frame's rows with -1 (not associated) for the dropped ones. The classifier's
label is what the estimator follows: a landmark the classifier calls a vehicle is dropped too, a
vehicle it calls static is kept (``[perception] class_error``).
"""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np

from coloc.core.frame import Frame

#: Class of a vehicle row (couplers.sensing.road_users CLASS_VEHICLE).
CLASS_VEHICLE = 2


def without_vehicle_rows(frame: Frame) -> tuple[Frame, np.ndarray | None]:
    """(the frame without its vehicle-class rows, the kept row indices); (frame, None) when it has none."""
    cls = frame.v2f_class
    if cls is None:
        return frame, None
    keep = np.flatnonzero(np.asarray(cls) != CLASS_VEHICLE)
    if keep.size == cls.shape[0]:
        return frame, None
    truth = frame.truth
    if truth is not None:
        kind = truth.v2f_kind[keep] if truth.v2f_kind is not None else None
        truth = replace(truth, v2f_feature=np.asarray(truth.v2f_feature)[keep], v2f_kind=kind)
    sensor = frame.v2f_sensor
    if sensor is not None:  # sensor-frame rows (coloc.core.detections): every per-row array keeps the same rows
        sensor = replace(sensor, **{f.name: np.asarray(getattr(sensor, f.name))[keep] for f in fields(sensor)})
    return replace(frame, v2f_z=frame.v2f_z[keep], v2f_owner=np.asarray(frame.v2f_owner)[keep],
                   v2f_R=frame.v2f_R[keep], v2f_class=np.asarray(cls)[keep], truth=truth,
                   v2f_sensor=sensor), keep


def expand_rows(values: np.ndarray | None, keep: np.ndarray | None, n_rows: int, fill=-1):
    """``values`` of the kept rows spread back over the frame's ``n_rows`` rows (``fill`` elsewhere)."""
    if keep is None or values is None:
        return values
    out = np.full(n_rows, fill, dtype=np.asarray(values).dtype)
    out[keep] = values
    return out
