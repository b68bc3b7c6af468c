"""A pinhole camera that renders a scene with exact per-pixel ground truth.

Camera frame (OpenCV / KITTI): x right, y down, z forward. One ray per pixel centre
(u + 0.5, v + 0.5) through the pinhole, all at one `time` (global shutter: moving bodies are
placed at that time). Shading is plain, per class: `COLORS[semantic]` (or each body's own
`Body.color` with `body_colors=True`) times (0.35 + 0.65 |n . l|), a mild darkening with
distance (fog) so depth reads, a body's `shade` (deep shadow, dark paint), and `SKY_COLOR`
where nothing is hit. The LiDAR halo never
shows in the camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.simulate.colors import COLORS, SKY_COLOR
from app.simulate.raycast import RayCaster
from app.simulate.scene import Scene

FOG_DISTANCE = 80.0  # m: colours fade to 55 % + 45 % * exp(-distance / FOG_DISTANCE)


@dataclass(frozen=True)
class CameraConfig:
    """KITTI image_02-like intrinsics (rectified colour camera)."""

    width: int = 1242
    height: int = 375
    fx: float = 721.5377
    fy: float = 721.5377
    cx: float = 609.5593
    cy: float = 172.854
    max_range: float = 150.0

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def P(self) -> np.ndarray:
        """3x4 projection [K | 0] of camera-frame points."""
        return np.hstack([self.K, np.zeros((3, 1))])


@dataclass
class Render:
    rgb: np.ndarray  # (H, W, 3) uint8
    semantic: np.ndarray  # (H, W) uint16 class id, 0 = sky / miss
    instance: np.ndarray  # (H, W) int32 body instance id, 0 for stuff and sky
    body: np.ndarray  # (H, W) int32 index into scene.bodies, -1 = sky
    depth: np.ndarray  # (H, W) float32 camera z (m), inf = sky


def pixel_rays(config: CameraConfig) -> np.ndarray:
    """(H*W, 3) unit ray directions in the camera frame, row-major over pixel centres."""
    u = (np.arange(config.width) + 0.5 - config.cx) / config.fx
    v = (np.arange(config.height) + 0.5 - config.cy) / config.fy
    d = np.stack(np.broadcast_arrays(u[None, :], v[:, None], 1.0), axis=-1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def render(
    caster: RayCaster,
    scene: Scene,
    T_world_cam: np.ndarray,
    time: float,
    config: CameraConfig = CameraConfig(),
    light_dir: tuple[float, float, float] = (0.3, -0.4, 0.85),
    body_colors: bool = False,
) -> Render:
    """Render the scene seen from `T_world_cam` (camera -> world, 4x4) at `time`.

    `light_dir` is a world direction towards the light. Colours are `COLORS[semantic]` (a class
    missing from COLORS falls back to the body's colour), or `Body.color` with `body_colors`.
    """
    T = np.asarray(T_world_cam, dtype=np.float64)
    d_cam = pixel_rays(config)
    d_world = d_cam @ T[:3, :3].T
    hits = caster.cast_from(T[:3, 3], d_world, time, config.max_range)
    H, W = config.height, config.width
    hit = hits.body >= 0
    body_idx = hits.body[hit]
    semantic_of = np.array([b.semantic for b in scene.bodies] or [0], dtype=np.uint16)
    instance_of = np.array([b.instance for b in scene.bodies] or [0], dtype=np.int32)
    color_of = np.array(
        [b.color if body_colors else COLORS.get(b.semantic, b.color) for b in scene.bodies]
        or [(0, 0, 0)],
        dtype=np.float64,
    )

    semantic = np.zeros(H * W, dtype=np.uint16)
    instance = np.zeros(H * W, dtype=np.int32)
    depth = np.full(H * W, np.inf, dtype=np.float32)
    semantic[hit] = semantic_of[body_idx]
    instance[hit] = instance_of[body_idx]
    depth[hit] = hits.distance[hit] * d_cam[hit, 2]

    light = np.asarray(light_dir, dtype=np.float64)
    light = light / np.linalg.norm(light)
    lambert = np.abs(hits.normal[hit] @ light)
    fog = 0.55 + 0.45 * np.exp(-hits.distance[hit] / FOG_DISTANCE)
    rgb = np.empty((H * W, 3))
    rgb[:] = SKY_COLOR
    shade_of = np.array([b.shade for b in scene.bodies] or [1.0], dtype=np.float64)
    rgb[hit] = color_of[body_idx] * ((0.35 + 0.65 * lambert) * fog * shade_of[body_idx])[:, None]
    return Render(
        rgb=np.clip(np.rint(rgb), 0, 255).astype(np.uint8).reshape(H, W, 3),
        semantic=semantic.reshape(H, W),
        instance=instance.reshape(H, W),
        body=hits.body.reshape(H, W),
        depth=depth.reshape(H, W),
    )
