"""Device code of warpfem: Warp kernels and functions only, one module per pipeline stage.

Shipped as ``warpfem.kernels`` (setuptools package-dir); never import it as a top-level ``kernels``.
"""
