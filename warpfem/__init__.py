"""warpfem: dense surface meshes animated through simplified tetrahedral meshes, in NVIDIA Warp."""

__version__ = "0.1.0"
