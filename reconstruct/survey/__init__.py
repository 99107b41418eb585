"""Drone surveys: one moving camera, neighbouring frames as stereo pairs. Inputs and GPS,
poses (pycolmap), dense pairs through :mod:`prism3d.reconstruct.stereo`'s matcher, fusion,
DSM and nDSM, the true orthophoto and the georeferenced products (``run.run_survey``)."""
