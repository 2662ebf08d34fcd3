"""The simulation: :class:`~warpfem.sim.model.Model` and :class:`~warpfem.sim.model.State`, and the solver's stages.

Corotational linear FEM, vertex-tet collisions with distance-field penalties, implicit Euler solved by
preconditioned CG, all as Warp launches over flat arrays. It receives arrays: it never imports
preprocessing, output or CLI code.
"""
