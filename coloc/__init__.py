"""coloc: estimators for cooperative vehicle localization.

Imports numpy, numba and scipy only (gtsam for the factor graph, when used): never libsumo,
couplers or experiments. A frame of measurements (:class:`coloc.core.frame.Frame`) is the only input.

Layers, each importing only the ones below it (``tests/coloc/test_layers.py``):

* :mod:`coloc.methods`: one module per estimator and the registry of method names
  (:mod:`coloc.methods.registry`);
* :mod:`coloc.inference`: association BP, consensus, Gaussian information algebra, feature
  tracks, the BPA-L loop, particle utilities;
* :mod:`coloc.kernels`: numba kernels;
* :mod:`coloc.core`: frame, estimator protocols, models, vehicle bookkeeping.
"""

from coloc.core.frame import Frame, StepEstimate, Truth
from coloc.core.protocol import Estimator, KnownAssociationEstimator

__all__ = ["Frame", "StepEstimate", "Truth", "Estimator", "KnownAssociationEstimator"]
