"""Viewer modes, one module each; `MODES` is the order of the session's "Mode" dropdown (the
first is the default). A new mode is a `Mode` subclass (see `base`) added here."""

from app.viewer.modes.base import Mode
from app.viewer.modes.clutter import ClutterMode
from app.viewer.modes.guardrails import GuardrailMode
from app.viewer.modes.models import ModelMode
from app.viewer.modes.pillars import PillarMode
from app.viewer.modes.qa import QAMode

MODES: tuple[type[Mode], ...] = (PillarMode, ClutterMode, GuardrailMode, ModelMode, QAMode)

__all__ = ["MODES", "ClutterMode", "GuardrailMode", "Mode", "ModelMode", "PillarMode", "QAMode"]
