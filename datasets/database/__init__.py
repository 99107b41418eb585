"""The target database (Parquet + NPZ + YAML, datasets/FORMAT.md), what goes into it
(meshes, scans) and how a target list resolves against it. Builds on :mod:`.models`."""
