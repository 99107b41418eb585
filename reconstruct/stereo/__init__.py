"""One prism shot to a metric scan: chessboard calibration, rectification, the numba stereo
matcher and its sub-pixel refinement, triangulation, meshing and the paper's flatness test.
Imports nothing else of :mod:`prism3d.reconstruct`."""
