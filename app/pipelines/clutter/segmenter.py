"""Image segmenter of the clutter pipeline (Lee et al. 2020, step 1: segment the camera image).

The paper removes the LiDAR points that fall under image masks of people and vehicles. This
module turns RGB frames into per-pixel *clutter class maps* (uint8, H x W):

    0 = not clutter, 1..8 = CLUTTER_CLASSES (person, rider, car, truck, bus, train/tram,
    motorcycle, bicycle), i.e. Cityscapes ids 11..18 shifted down by 10.

- `Segmenter`: the protocol any model implements, so another network can be plugged in.
- `ESPNetv2Segmenter`: our ESPNetv2 (s = 2.0, Cityscapes weights), loaded on first use.
- `CachedSegmenter`: one compressed PNG per frame keyed by segmenter, weights and image file,
  so reruns and the review viewer never run the network twice for the same image.
- `overlay_png`: the image with the clutter classes blended in, for review and reports.
"""

from __future__ import annotations

import hashlib
import os
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import cv2
import numpy as np

from app.core.bounds import GAMMA_RANGE
from app.core.errors import ConfigError, DependencyMissingError, InputError
from app.core.progress import Progress
from app.io.survey import Frame, Survey

if TYPE_CHECKING:
    import torch

CLUTTER_CLASSES = ("person", "rider", "car", "truck", "bus", "train", "motorcycle", "bicycle")
# Cityscapes train id -> clutter code (0 = not clutter); train covers trams.
CITYSCAPES_TO_CLUTTER = {11 + i: 1 + i for i in range(len(CLUTTER_CLASSES))}
_LUT = np.zeros(256, dtype=np.uint8)
for _city, _code in CITYSCAPES_TO_CLUTTER.items():
    _LUT[_city] = _code

# RGB per clutter code, chosen to be told apart at a glance (index 0 unused).
CLUTTER_COLORS = np.array(
    [
        (0, 0, 0),
        (230, 25, 75),  # person: red
        (245, 130, 48),  # rider: orange
        (0, 110, 255),  # car: blue
        (70, 240, 240),  # truck: cyan
        (145, 30, 180),  # bus: purple
        (240, 50, 230),  # train: magenta
        (255, 225, 25),  # motorcycle: yellow
        (60, 180, 75),  # bicycle: green
    ],
    dtype=np.uint8,
)

WEIGHTS_FILE = "espnetv2_s_2.0_city_1024x512.pth"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
STRIDE = 16  # the encoder's total down-sampling: inputs are padded to a multiple of it
PREPROCESS_VERSION = (
    "fit-down-reflect16-gamma-v2"  # part of the cache key: bump when preprocessing changes
)


def cityscapes_to_clutter(class_map: np.ndarray) -> np.ndarray:
    """Cityscapes train ids (uint8 map) -> clutter codes 0..8."""
    return _LUT[class_map]


@runtime_checkable
class Segmenter(Protocol):
    """Anything that turns RGB images into clutter class maps.

    `name` and `fingerprint` identify the model and its weights/settings in cache keys: two
    segmenters with equal (name, fingerprint) must give equal maps for equal images.
    """

    name: str

    @property
    def fingerprint(self) -> str: ...

    def segment(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """RGB uint8 (H, W, 3) images -> clutter class maps, uint8 (H, W) each, same sizes."""
        ...


def _network_size(width: int, height: int, max_size: tuple[int, int]) -> tuple[int, int]:
    """(w, h) the image is resized to: fit inside max_size keeping the aspect ratio, never up."""
    scale = min(1.0, max_size[0] / width, max_size[1] / height)
    return max(1, round(width * scale)), max(1, round(height * scale))


def brightening_lut(gamma: float) -> np.ndarray:
    """uint8 -> uint8 table of v' = 255 (v / 255) ** gamma (gamma < 1 lifts the dark tones)."""
    return np.round(255.0 * (np.arange(256) / 255.0) ** gamma).astype(np.uint8)


def _ceil_to(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


class ESPNetv2Segmenter:
    """ESPNetv2 (s = 2.0) trained on Cityscapes, run on CPU or GPU.

    Preprocessing (measured on SemanticKITTI 04/05/08, 30 frames, clutter points vs. the labels):
    the image is only ever *down*-scaled to fit `input_size` (W, H), keeping its aspect ratio,
    then reflect-padded at the bottom and right to a multiple of 16, and the scores are cropped
    back. A KITTI frame (1242x375 or 1226x370) is thus padded to 1248x384 with no resampling at
    all. Point IoU of the clutter classes: 0.539 this way, 0.534 stretching to 1248x384, 0.528
    up-scaling to fit and padding; stretching 1.5x larger (1872x576) is clearly worse (0.478
    vs 0.528 at 1248x384 on 12 of the frames), so small images are not enlarged either.

    `gamma` maps the image's tones v' = 255 (v / 255)^gamma before anything else: below 1 it
    lifts the dark tones, where KITTI's objects in shadow sit (bench/clutter_brightening.py:
    the masks' point IoU rises on 04 / 05 / 08 at every gamma from 0.9 to 0.4; the pipeline
    chose 0.9, `ClutterConfig.image_gamma`). 1 is the network as published.
    """

    name = "espnetv2-s2.0-cityscapes"

    def __init__(
        self,
        weights_dir: Path | None = None,
        device: str = "cpu",
        batch_size: int = 4,
        input_size: tuple[int, int] = (1248, 384),
        gamma: float = 1.0,
    ):
        if weights_dir is None:
            from app.core.settings import get_settings

            weights_dir = get_settings().weights_dir
        self.weights_path = Path(weights_dir) / WEIGHTS_FILE
        if not self.weights_path.is_file():
            raise DependencyMissingError(
                f"{self.weights_path}: ESPNetv2 segmentation weights are missing; put "
                f"{WEIGHTS_FILE} in {Path(weights_dir)} or set MMSCLEAN_WEIGHTS_DIR to the folder "
                "holding it"
            )
        width, height = input_size
        if width <= 0 or height <= 0 or width % STRIDE or height % STRIDE:
            raise ConfigError(
                "input_size", f"must be positive multiples of {STRIDE} (got {input_size})"
            )
        if batch_size < 1:
            raise ConfigError("batch_size", f"must be at least 1 (got {batch_size})")
        if not GAMMA_RANGE[0] <= gamma <= GAMMA_RANGE[1]:
            low, high = GAMMA_RANGE
            raise ConfigError("gamma", f"must be within {low:g}-{high:g} (got {gamma})")
        self.device = device
        self.batch_size = batch_size
        self.input_size = (width, height)
        self.gamma = float(gamma)
        self._lut = brightening_lut(self.gamma)
        self._model: torch.nn.Module | None = None
        self._fingerprint: str | None = None

    @property
    def fingerprint(self) -> str:
        """Weights sha256 + size + input size + preprocessing version (the cache key part)."""
        if self._fingerprint is None:
            data = self.weights_path.read_bytes()
            sha = hashlib.sha256(data).hexdigest()[:16]
            w, h = self.input_size
            self._fingerprint = f"{sha}-{len(data)}-{w}x{h}-g{self.gamma:g}-{PREPROCESS_VERSION}"
        return self._fingerprint

    @property
    def model(self) -> torch.nn.Module:
        """The network, built and loaded (strict) on first use."""
        if self._model is None:
            import torch

            from app.pipelines.clutter.espnetv2 import ESPNetv2Seg

            try:
                # The published file holds CUDA tensors: map them to the CPU first.
                state = torch.load(self.weights_path, map_location="cpu", weights_only=True)
                model = ESPNetv2Seg()
                model.load_state_dict(state, strict=True)
            except Exception as exc:  # any failure means the file is unusable
                reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise DependencyMissingError(
                    f"{self.weights_path}: not a usable ESPNetv2 s=2.0 state dict ({reason})"
                ) from None
            self._model = model.eval().to(self.device)
        return self._model

    def segment(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """RGB uint8 images -> clutter class maps (0 = not clutter, 1..8 = CLUTTER_CLASSES)."""
        return [cityscapes_to_clutter(m) for m in self.cityscapes_maps(images)]

    def cityscapes_maps(self, images: Sequence[np.ndarray]) -> list[np.ndarray]:
        """RGB uint8 images -> Cityscapes train-id maps (uint8, 0..19), each at its image size."""
        out: list[np.ndarray | None] = [None] * len(images)
        groups: dict[tuple[int, int], list[int]] = {}
        for i, image in enumerate(images):
            if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
                raise ValueError(f"image {i}: expected (H, W, 3) uint8 RGB, got {image.shape}")
            h, w = image.shape[:2]
            groups.setdefault(_network_size(w, h, self.input_size), []).append(i)
        for size, members in groups.items():
            for start in range(0, len(members), self.batch_size):
                chunk = members[start : start + self.batch_size]
                maps = self._run([images[i] for i in chunk], size)
                for i, class_map in zip(chunk, maps, strict=True):
                    out[i] = class_map
        return out  # type: ignore[return-value]

    def _run(self, images: list[np.ndarray], size: tuple[int, int]) -> list[np.ndarray]:
        """One batch of images that all resize to `size` (w, h)."""
        import torch

        w, h = size
        pad_w, pad_h = _ceil_to(w, STRIDE) - w, _ceil_to(h, STRIDE) - h
        batch = []
        for image in images:
            x = self._lut[image]
            if (x.shape[1], x.shape[0]) != (w, h):
                x = cv2.resize(x, (w, h), interpolation=cv2.INTER_AREA)
            if pad_w or pad_h:
                # Mirrored content, not a flat colour, so that no fake edge meets the border.
                x = cv2.copyMakeBorder(x, 0, pad_h, 0, pad_w, cv2.BORDER_REFLECT_101)
            batch.append(x)
        model = self.model
        with torch.inference_mode():
            x = torch.from_numpy(np.stack(batch)).to(self.device)
            x = x.permute(0, 3, 1, 2).float().div_(255.0)
            mean = torch.tensor(IMAGENET_MEAN, device=self.device).view(1, 3, 1, 1)
            std = torch.tensor(IMAGENET_STD, device=self.device).view(1, 3, 1, 1)
            labels = model((x - mean) / std).argmax(1)[:, :h, :w].to(torch.uint8).cpu().numpy()
        maps = []
        for image, class_map in zip(images, labels, strict=True):
            height, width = image.shape[:2]
            if (width, height) != (w, h):
                class_map = cv2.resize(class_map, (width, height), interpolation=cv2.INTER_NEAREST)
            maps.append(np.ascontiguousarray(class_map))
        return maps


def _write_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary name beside `path`, then rename: never a half-written file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


class CachedSegmenter:
    """Per-frame cache in front of a `Segmenter`, keyed by image *file*.

    Key: segmenter name + fingerprint (weights sha/size, settings) + absolute image path + its
    mtime and size; a changed image or model gets a new entry. Each map is a single-channel PNG
    (lossless, compressed, viewable) under `cache_dir/<segmenter name>/`.
    """

    def __init__(self, inner: Segmenter, cache_dir: Path | None = None, chunk: int = 8):
        if cache_dir is None:
            from app.core.settings import get_settings

            cache_dir = get_settings().cache_dir / "segmentation"
        self.inner = inner
        self.cache_dir = Path(cache_dir) / inner.name
        self.chunk = chunk  # images loaded at once for the network (bounds memory)
        self.hits = 0
        self.misses = 0

    @property
    def name(self) -> str:
        return self.inner.name

    def cache_path(self, image_path: Path) -> Path:
        """Where the map of this image file (as it is now) is cached."""
        path = Path(image_path).resolve()
        try:
            st = path.stat()
        except OSError:
            raise InputError(path, "is missing or not readable") from None
        parts = (self.inner.name, self.inner.fingerprint, str(path), st.st_mtime_ns, st.st_size)
        key = hashlib.sha256("|".join(map(str, parts)).encode()).hexdigest()[:32]
        return self.cache_dir / f"{key}.png"

    def lookup(self, image_path: Path) -> np.ndarray | None:
        """The cached map of this image, or None (review: never runs the network)."""
        cached = self.cache_path(image_path)
        if not cached.is_file():
            return None
        class_map = cv2.imread(str(cached), cv2.IMREAD_UNCHANGED)
        if class_map is None or class_map.ndim != 2:
            return None  # unreadable entry: recompute
        return class_map

    def segment_files(self, image_paths: Sequence[Path]) -> list[np.ndarray]:
        """Clutter class maps of the image files, from the cache or computed and stored."""
        from app.io.images import read_rgb

        out: list[np.ndarray | None] = [self.lookup(p) for p in image_paths]
        todo = [i for i, m in enumerate(out) if m is None]
        self.hits += len(image_paths) - len(todo)
        self.misses += len(todo)
        for start in range(0, len(todo), self.chunk):
            chunk = todo[start : start + self.chunk]
            images = [read_rgb(Path(image_paths[i])) for i in chunk]
            for i, image, class_map in zip(chunk, images, self.inner.segment(images), strict=True):
                if class_map.shape != image.shape[:2]:
                    raise ValueError(
                        f"{self.inner.name} returned a {class_map.shape} map for a "
                        f"{image.shape[:2]} image"
                    )
                ok, png = cv2.imencode(".png", class_map.astype(np.uint8))
                if not ok:
                    raise RuntimeError(f"could not encode the class map of {image_paths[i]}")
                _write_atomic(self.cache_path(image_paths[i]), png.tobytes())
                out[i] = class_map
        return out  # type: ignore[return-value]


def overlay_png(image: np.ndarray, class_map: np.ndarray, path: Path, alpha: float = 0.55) -> Path:
    """Write `image` (RGB uint8) with each clutter class blended in its CLUTTER_COLORS colour."""
    if class_map.shape != image.shape[:2]:
        raise ValueError(f"class map {class_map.shape} does not match image {image.shape[:2]}")
    out = image.astype(np.float32)
    mask = class_map > 0
    colours = CLUTTER_COLORS[np.clip(class_map, 0, len(CLUTTER_CLASSES))].astype(np.float32)
    out[mask] = (1.0 - alpha) * out[mask] + alpha * colours[mask]
    blended = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    ok, png = cv2.imencode(".png", cv2.cvtColor(blended, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"could not encode the overlay for {path}")
    path = Path(path)
    _write_atomic(path, png.tobytes())
    return path


def segmented_class_maps(
    survey: Survey,
    camera: str,
    segmenter: Segmenter | None = None,
    progress: Progress | None = None,
    cache_dir: Path | None = None,
) -> tuple[Callable[[Frame], np.ndarray], CachedSegmenter]:
    """Segment every frame's image of `camera` in batches (cached per image file, under
    `cache_dir`, default the settings' cache), then hand the pipeline a per-frame lookup."""
    if segmenter is None:
        segmenter = ESPNetv2Segmenter()
    cached = CachedSegmenter(segmenter, cache_dir)
    paths = [f.image_paths[camera] for f in survey.frames if camera in f.image_paths]
    step = max(cached.chunk, 1)
    for start in range(0, len(paths), step):
        if progress:
            progress("segmentation", start / max(len(paths), 1))
        cached.segment_files(paths[start : start + step])

    def class_map(frame: Frame) -> np.ndarray:
        return cached.segment_files([frame.image_paths[camera]])[0]

    return class_map, cached
