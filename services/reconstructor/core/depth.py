"""Metric depth of a video frame, for cross-modal metric alignment (``METRIC_DEPTH``).

* ``sensor`` (default): the frame's own depth (an RGB-D camera, or the simulator's).
* ``depth-anything-v2``: monocular metric depth from Depth-Anything-V2 through ``transformers``
  (optional extra, imported when the backend is created; the model id is configurable and may be a
  local directory). The paper uses it because its robot records RGB only.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod

import numpy as np

from shared.registry import BackendConfig, Registry

from .errors import BackendUnavailableError, MissingDepthError
from .frames import PosedImage

log = logging.getLogger(__name__)


class MetricDepth(ABC):
    """Predicts or reads a metric z-depth image (float32, 0 = unknown) for a frame."""

    name: str = ""

    @abstractmethod
    def depth(self, image: PosedImage) -> np.ndarray:
        """(H, W) float32 metric z-depth of ``image``; 0 where unknown."""


METRIC_DEPTH: Registry[MetricDepth] = Registry("metric depth")
DEFAULT_METRIC_DEPTH = "sensor"


class SensorDepthConfig(BackendConfig):
    pass


@METRIC_DEPTH.register("sensor", SensorDepthConfig)
class SensorDepth(MetricDepth):
    name = "sensor"

    def __init__(self, config: SensorDepthConfig | None = None):
        self.config = config or SensorDepthConfig()

    def depth(self, image: PosedImage) -> np.ndarray:
        if image.depth_m is None:
            raise MissingDepthError(
                f"frame {image.index} has no depth; use metric_depth='depth-anything-v2' for RGB-only recordings"
            )
        d = np.asarray(image.depth_m, np.float32)
        return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)


class DepthAnythingConfig(BackendConfig):
    """Depth-Anything-V2 metric model through transformers (``pip install transformers``)."""

    model_id: str = "depth-anything/Depth-Anything-V2-Metric-Indoor-Small-hf"
    device: str = "auto"  # auto: cuda when available
    local_files_only: bool = True  # never reach a model hub unless told to


@METRIC_DEPTH.register("depth-anything-v2", DepthAnythingConfig)
class DepthAnythingV2(MetricDepth):
    name = "depth-anything-v2"

    def __init__(self, config: DepthAnythingConfig | None = None):
        self.config = cfg = config or DepthAnythingConfig()
        try:
            import torch
            from transformers import AutoImageProcessor, AutoModelForDepthEstimation
        except ImportError as exc:
            raise BackendUnavailableError(
                f"depth-anything-v2 needs the transformers package ({exc}); pip install transformers"
            ) from exc
        self._torch = torch
        device = cfg.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self._device = device
        try:
            self._processor = AutoImageProcessor.from_pretrained(cfg.model_id, local_files_only=cfg.local_files_only)
            self._model = AutoModelForDepthEstimation.from_pretrained(
                cfg.model_id, local_files_only=cfg.local_files_only
            ).to(device).eval()
        except (OSError, ValueError) as exc:
            raise BackendUnavailableError(f"cannot load depth model {cfg.model_id!r}: {exc}") from exc

    def depth(self, image: PosedImage) -> np.ndarray:
        torch = self._torch
        h, w = image.rgb.shape[:2]
        inputs = self._processor(images=image.rgb, return_tensors="pt").to(self._device)
        with torch.no_grad():
            pred = self._model(**inputs).predicted_depth  # (1, h', w') metres
        pred = torch.nn.functional.interpolate(pred[:, None], size=(h, w), mode="bicubic", align_corners=False)
        d = pred[0, 0].float().cpu().numpy()
        return np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
