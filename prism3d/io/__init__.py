"""File formats users already know: PFM, OpenCV FileStorage YAML, PLY, depth maps,
images; every writer is atomic."""
