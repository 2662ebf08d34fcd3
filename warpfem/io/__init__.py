"""Output: animated USD files, and a headless preview renderer with image and video writers."""
