"""The ``mono`` backend: SLAM3R (PKU-VCL-3DV/SLAM3R, CVPR 2025) as in the paper; an optional GPU extra.

Nothing here is imported until the backend is created, so the default install never needs torch
CUDA, SLAM3R or its weights. Configure it with a local checkout and local checkpoints (the system
never downloads models)::

    RECONSTRUCTORS.create("mono", {
        "repo_path": "/opt/SLAM3R",                       # git clone of PKU-VCL-3DV/SLAM3R
        "i2p_weights": "/models/slam3r_i2p",              # Image2PointsModel checkpoint (dir or .pth)
        "l2w_weights": "/models/slam3r_l2w",              # Local2WorldModel checkpoint (dir or .pth)
        "device": "cuda",
    })

What the adapter does: the region's RGB frames are written as an image sequence, SLAM3R's offline
pipeline (``scene_recon_pipeline_offline``: I2P local windows + L2W registration into the frame of
its initial reference view) reconstructs them, and its points (OpenCV axes of that reference camera,
unknown scale) are rotated into z-up axes with the camera at the origin looking along +x. The cloud
is reported non-metric; metric alignment then recovers the scale and, from the matched frame, the
heading of the reference view (``theta_t``). The rotation assumes a level reference camera (the
recordings start with level frames at the tour start). The cloud has no view directions: SLAM3R
writes points without the camera poses of its frame, and the recording's poses are in another
frame at another scale, so where each point was seen from is not known.
"""

from __future__ import annotations

import importlib
import logging
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from pydantic import Field

from shared.cloud import PointCloud
from shared.registry import BackendConfig

from .errors import BackendUnavailableError, EmptyRecordingError
from .regional import RECONSTRUCTORS, RegionalCloud, RegionalReconstructor, level_camera_to_local

log = logging.getLogger(__name__)


class Slam3rConfig(BackendConfig):
    """SLAM3R offline reconstruction; paths are local (a checkout and two checkpoints)."""

    repo_path: str | None = None  # added to sys.path when given; else ``slam3r`` must be importable
    i2p_weights: str | None = None
    l2w_weights: str | None = None
    device: str = "cuda"
    img_size_px: int = Field(224, ge=64, le=1024)
    keyframe_stride: int = Field(3, ge=-1)  # -1: SLAM3R's adaptive stride
    win_r: int = Field(3, ge=1)
    num_scene_frame: int = Field(10, ge=1)
    conf_thres_i2p: float = 1.5
    conf_thres_l2w: float = 12.0
    max_frames: int = Field(2000, ge=2)
    extra_args: dict = Field(default_factory=dict)  # passed through to SLAM3R's pipeline arguments


@RECONSTRUCTORS.register("mono", Slam3rConfig)
class Slam3rReconstructor(RegionalReconstructor):
    """Monocular neural SLAM reconstruction (non-metric)."""

    name = "mono"
    metric = False

    def __init__(self, config: Slam3rConfig | None = None):
        self.config = cfg = config or Slam3rConfig()
        if cfg.i2p_weights is None or cfg.l2w_weights is None:
            raise BackendUnavailableError(
                "the mono (SLAM3R) backend needs i2p_weights and l2w_weights: local Image2PointsModel "
                "and Local2WorldModel checkpoints (see services/reconstructor/core/slam3r.py)"
            )
        if cfg.repo_path is not None:
            if not Path(cfg.repo_path).is_dir():
                raise BackendUnavailableError(f"SLAM3R repo_path {cfg.repo_path!r} is not a directory")
            if cfg.repo_path not in sys.path:
                sys.path.insert(0, cfg.repo_path)
        try:
            import torch

            self._torch = torch
            models = importlib.import_module("slam3r.models")
            self._offline = importlib.import_module("slam3r.pipeline.recon_offline_pipeline")
            self._seq = importlib.import_module("slam3r.datasets.wild_seq")
        except ImportError as exc:
            raise BackendUnavailableError(
                f"SLAM3R is not installed ({exc}); clone PKU-VCL-3DV/SLAM3R, install its requirements "
                "and set repo_path"
            ) from exc
        if cfg.device.startswith("cuda") and not torch.cuda.is_available():
            raise BackendUnavailableError("SLAM3R needs a CUDA GPU and none is available")
        self._i2p = self._load(models.Image2PointsModel, cfg.i2p_weights)
        self._l2w = self._load(models.Local2WorldModel, cfg.l2w_weights)

    def _load(self, cls, weights: str):
        p = Path(weights)
        if not p.exists():
            raise BackendUnavailableError(f"SLAM3R checkpoint {weights!r} does not exist")
        if p.is_dir():
            model = cls.from_pretrained(str(p))
        else:
            raise BackendUnavailableError(
                f"{weights!r}: give a from_pretrained directory (config.json + weights) for {cls.__name__}"
            )
        return model.to(self.config.device).eval()

    def reconstruct(self, region, label_names=None) -> RegionalCloud:
        import cv2

        cfg = self.config
        images = region.images[: cfg.max_frames]
        if len(images) < 2:
            raise EmptyRecordingError(f"region {region.region}: SLAM3R needs at least 2 frames")
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="slam3r-") as tmp:
            img_dir = Path(tmp) / "frames"
            out_dir = Path(tmp) / "out"
            img_dir.mkdir()
            out_dir.mkdir()
            for k, im in enumerate(images):
                cv2.imwrite(str(img_dir / f"{k:06d}.png"), im.rgb[:, :, ::-1])
            dataset = self._seq.Seq_Data(img_dir=str(img_dir), img_size=cfg.img_size_px, silent=True)
            args = SimpleNamespace(
                keyframe_stride=cfg.keyframe_stride, win_r=cfg.win_r, num_scene_frame=cfg.num_scene_frame,
                initial_winsize=5, conf_thres_l2w=cfg.conf_thres_l2w, conf_thres_i2p=cfg.conf_thres_i2p,
                num_points_save=2_000_000, norm_input=False, save_frequency=3, save_each_frame=False,
                retrieve_freq=1, update_buffer_intv=1, buffer_size=100, buffer_strategy="reservoir",
                max_num_register=10, save_preds=False, save_for_eval=False, save_online=False,
                perframe=1, device=cfg.device, test_name=f"region{region.region}",
                **cfg.extra_args,
            )
            with self._torch.no_grad():
                self._offline.scene_recon_pipeline_offline(self._i2p, self._l2w, dataset, args, str(out_dir))
            plys = sorted(out_dir.rglob("*.ply"))
            if not plys:
                raise EmptyRecordingError(f"region {region.region}: SLAM3R wrote no cloud")
            raw = PointCloud.load(plys[-1])
        xyz = level_camera_to_local(raw.xyz)
        cloud = PointCloud(xyz, raw.rgb, None, dict(label_names or {}))  # no view_dirs: see the module docstring
        return RegionalCloud(
            region=region.region, cloud=cloud, metric=False, camera_origin_m=np.zeros(3),
            backend=self.name, frames_used=len(images), points_in=len(raw),
            timings_s={"slam3r": time.perf_counter() - t0},
        )
