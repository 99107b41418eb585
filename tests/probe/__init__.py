"""The bad-input probe of issue 27: a reproducible list of bad command lines
(:mod:`tests.probe.cases`), run in-process by ``tests/root/test_bad_inputs.py`` and in
subprocesses by ``benchmarks/probe_bad_inputs.py``."""
