"""The jobs that fill the database and train recognisers: render and feature jobs,
hard-negative mining, the cached recognisers and their pre-training. Builds on the other
sub-packages; runs on :mod:`prism3d.datasets.runner` (local processes or Dask)."""
