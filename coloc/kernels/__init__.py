"""numba kernels (``njit(cache=True)``) of the hot loops, each checked against a numpy reference in
the tests: the Gaussian ICP's BPA-L passes (:mod:`~coloc.kernels.icp`), the GNSS tracker step
(:mod:`~coloc.kernels.kalman`) and the particle-pair kernels of ICP-DA-PF (:mod:`~coloc.kernels.pf`).
Kernels import only :mod:`coloc.core` (and numpy, numba)."""
