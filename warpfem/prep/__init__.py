"""Preprocessing: load and repair a dense mesh, simplify it, tetrahedralize, embed, and precompute what the model needs.

Runs on the host (NumPy, libigl, Netgen, and Warp kernels for the heavy queries); results are cached per
mesh and parameters. Nothing here imports the simulation, output or CLI code.
"""
