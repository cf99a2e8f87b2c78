"""The data and models every layer shares: the frame of measurements and the step estimate
(:mod:`~coloc.core.frame`), the estimator protocols (:mod:`~coloc.core.protocol`), the motion
and measurement models (:mod:`~coloc.core.models`) and vehicle bookkeeping across frames
(:mod:`~coloc.core.vehicles`). Imports numpy and scipy only, nothing else of coloc."""
