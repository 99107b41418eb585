"""Simulated scenes with exact truth: field scenes for whole-scene ATR, car parks, drone
flights over them, a virtual camera. Builds on :mod:`.models` and :mod:`.database`."""
