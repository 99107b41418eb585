"""Scans to 360-degree models: pairwise registration (FPFH + RANSAC, ICP), joint multiview
refinement, stitching, the object frame and fusion. Builds on :mod:`prism3d.reconstruct.stereo`
only."""
