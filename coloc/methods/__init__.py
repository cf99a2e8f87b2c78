"""The estimators, one module per method (the infrastructure methods ``rsu_bp`` and ``sme`` run
online in :mod:`~coloc.methods.infra`, ``fg_topology_new`` in :mod:`~coloc.methods.fg_topology`
beside Gulati's batch graphs); :mod:`~coloc.methods.rsu_bp` and :mod:`~coloc.methods.sme` also
hold the batch filters of their source papers' studies, :mod:`~coloc.methods.centralized` the
centralized Kalman filter the ICP is tested against. Methods import :mod:`coloc.inference`,
:mod:`coloc.kernels` and :mod:`coloc.core`."""
