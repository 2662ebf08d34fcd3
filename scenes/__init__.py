"""Scene files shipped with warpfem (``warpfem.scenes``); every key is documented in README.md here."""
