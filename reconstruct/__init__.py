"""prism3d.reconstruct: calibration, rectification, stereo matching, triangulation,
meshing, ICP stitching and the accuracy test."""
