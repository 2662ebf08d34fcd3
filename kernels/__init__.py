"""Device code of warpfem: Warp kernels and functions only, one module per pipeline stage.

Each module is named like the host module that launches it (``kernels.cg`` for ``warpfem.sim.cg``,
``kernels.distance`` for ``warpfem.prep.distance``, ``kernels.surface`` for ``warpfem.sim.surface``);
``grid`` and ``product`` are device helpers shared by them. The modules import one another relatively and
nothing else of warpfem (an import-linter contract checks it). Shipped as ``warpfem.kernels``
(setuptools package-dir); never import it as a top-level ``kernels``.
"""
