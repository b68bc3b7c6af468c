"""Pillar label colours: one palette for the four classes, model pre-labels lighter.

Human labels are drawn in full colour; a model pre-label is its class colour blended towards
white, the more the less confident the model was, so the eye goes to what is both unreviewed
and doubtful. Pillars with neither are grey.
"""

from __future__ import annotations

import numpy as np

from app.core.labels import PillarClass

CLASS_NAMES = {
    PillarClass.ground: "Ground",
    PillarClass.high_object: "High object",
    PillarClass.short_object: "Short object",
    PillarClass.phantom: "Phantom",
}
UNLABELLED = 4  # the fifth display class (no label from either source)
DISPLAY_CLASSES = (*(int(c) for c in PillarClass), UNLABELLED)
DISPLAY_NAMES = {**{int(c): n for c, n in CLASS_NAMES.items()}, UNLABELLED: "Unlabelled"}

PALETTE = np.array(
    [
        (150, 105, 60),  # ground: earth brown
        (30, 110, 230),  # high object: blue
        (250, 160, 0),  # short object: orange
        (225, 20, 140),  # phantom: magenta
        (135, 135, 135),  # unlabelled: grey
    ],
    dtype=np.float32,
)
MODEL_WHITE_MIN = 0.35  # blend towards white of a model label with confidence 1
MODEL_WHITE_MAX = 0.8  # ... and with confidence 0


def pillar_colors(human: np.ndarray, model: np.ndarray, confidence: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 colour per pillar from its human label, model label (-1: none) and the
    model's confidence."""
    klass = display_class(human, model)
    rgb = PALETTE[klass]
    from_model = (human < 0) & (model >= 0)
    if from_model.any():
        conf = np.clip(np.nan_to_num(confidence[from_model], nan=0.0), 0.0, 1.0)
        white = MODEL_WHITE_MAX - (MODEL_WHITE_MAX - MODEL_WHITE_MIN) * conf
        rgb[from_model] += (255.0 - rgb[from_model]) * white[:, None]
    return np.rint(rgb).astype(np.uint8)


def display_class(human: np.ndarray, model: np.ndarray) -> np.ndarray:
    """The class a pillar is shown as (and hidden with): human, else model, else UNLABELLED."""
    return np.where(human >= 0, human, np.where(model >= 0, model, UNLABELLED)).astype(np.int64)


def swatch_html(klass: int) -> str:
    r, g, b = (int(v) for v in PALETTE[klass])
    return (
        f'<span style="display:inline-block;width:0.9em;height:0.9em;margin-right:0.4em;'
        f'vertical-align:middle;background:rgb({r},{g},{b})"></span>'
    )
