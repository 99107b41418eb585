"""prism3d.datasets: built-in targets, the target database and its jobs."""
