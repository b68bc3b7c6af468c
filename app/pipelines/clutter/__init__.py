"""Clutter pipeline (Lee et al. 2020, and past it): camera masks, 3D expansion, free space
(DUFOMap), tracking, fusion, accumulation of the clean frames."""
