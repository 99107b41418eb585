"""Scoring simulated runs against their truth (surveys: poses, DSM, vehicle heights and
detections)."""
