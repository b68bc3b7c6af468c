"""Figure for the README (synthetic data): the guardrails `mmsclean run guardrail` reconstructs
on the sample survey, drawn over their points. Side view along each guardrail (horizontal axis:
the rail's main direction, vertical: height), points grey, the reconstructed mesh in colour.

Usage: .venv/bin/python docs/make_guardrail_figure.py
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from app.io import open_survey
from app.pipelines.guardrail.pipeline import GuardrailPipeline

DOCS = Path(__file__).resolve().parent
PIXELS_PER_METRE = 60


def side_view(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, length: float = 12.0):
    """The first `length` metres of one guardrail: points and shaded mesh, orthographic."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points[:, :2] - centre[:2], full_matrices=False)
    along = vt[0]
    u_pts = (points[:, :2] - centre[:2]) @ along
    start = u_pts.min()
    keep = u_pts < start + length
    u0, z0 = start - 0.3, points[:, 2].min() - 0.3
    width = int((length + 0.6) * PIXELS_PER_METRE)
    height = int((np.ptp(points[:, 2]) + 0.6) * PIXELS_PER_METRE)
    image = np.full((height, width, 3), 255, np.uint8)

    def pixels(xy: np.ndarray, z: np.ndarray) -> np.ndarray:
        u = ((xy - centre[:2]) @ along - u0) * PIXELS_PER_METRE
        v = height - 1 - (z - z0) * PIXELS_PER_METRE
        return np.stack([u, v], axis=1)

    p = pixels(points[keep, :2], points[keep, 2]).astype(int)
    inside = (p[:, 0] >= 0) & (p[:, 0] < width) & (p[:, 1] >= 0) & (p[:, 1] < height)
    image[p[inside, 1], p[inside, 0]] = (150, 150, 150)
    layer = image.copy()
    tri = pixels(vertices[:, :2], vertices[:, 2])[faces]  # (F, 3, 2)
    visible = (tri[:, :, 0].max(axis=1) >= 0) & (tri[:, :, 0].min(axis=1) < width)
    for corners in tri[visible].astype(np.int32):
        cv2.fillConvexPoly(layer, corners, (40, 110, 230))
    return cv2.addWeighted(layer, 0.55, image, 0.45, 0)


def main() -> None:
    sample = DOCS.parent / "data_samples" / "urban-60m"
    survey = open_survey(sample, "sim")
    result = GuardrailPipeline().run(survey)
    panels = []
    for g in result.guardrails:
        if g.model is None or len(g.model.faces) == 0:
            continue
        points = result.stage.points.xyz[g.points]
        panels.append(side_view(points, np.asarray(g.model.vertices), np.asarray(g.model.faces)))
    width = max(p.shape[1] for p in panels)
    padded = [cv2.copyMakeBorder(p, 0, 10, 0, width - p.shape[1], cv2.BORDER_CONSTANT,
                                 value=(255, 255, 255)) for p in panels]  # fmt: skip
    cv2.imwrite(str(DOCS / "guardrail_reconstruction.png"), np.vstack(padded))


if __name__ == "__main__":
    main()
