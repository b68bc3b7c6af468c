"""Scoring clutter runs against reference labels: the removal's error matrix and SA / DA / AA
(`removal_metrics`)."""
