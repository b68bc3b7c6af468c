"""Evaluation metrics: confusion matrices, precision / recall / F per class, confusion plots.

Pure numpy / scipy / cv2; imports nothing else of `app`, so pipelines, the CLI (`report.json`)
and benchmarks can all use it.
"""
