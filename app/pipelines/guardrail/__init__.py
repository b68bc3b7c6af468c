"""Guardrail pipeline (Matsumoto, Mori, Masuda): slices, camera-crop classifier, poles, unit
shapes, superimposition, pipe and beam reconstruction, mesh export."""
