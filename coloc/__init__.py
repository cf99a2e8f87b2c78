"""coloc: estimators for cooperative vehicle localization.

Imports numpy, numba and scipy only: never libsumo, couplers or experiments.
A frame of measurements (``coloc.frame.Frame``) is the only input.
"""

from coloc.frame import Frame, StepEstimate, Truth
from coloc.protocol import Estimator

__all__ = ["Frame", "StepEstimate", "Truth", "Estimator"]
