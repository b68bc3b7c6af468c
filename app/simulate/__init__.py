"""Synthetic mobile-mapping surveys with complete ground truth (scenes, scanners, camera)."""
