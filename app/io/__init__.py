"""Readers and writers, one module per format, behind `open_survey`; Survey and Frame types."""

from app.io.registry import FORMATS, open_survey
from app.io.survey import MAP_FRAME_ID, Camera, Frame, PointCloud, Survey

__all__ = ["FORMATS", "MAP_FRAME_ID", "Camera", "Frame", "PointCloud", "Survey", "open_survey"]
