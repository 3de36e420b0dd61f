"""The map-build job's progress while the map's one TSDF volume is fused (RgbdConfig.tsdf_scope "map").

That volume takes every noisy region's frames once more after the last region is reconstructed (15-17 s of a
47-52 s build on the two-floor house): the job reports each region it takes in as a "fusing" stage, and a
cancel asked for meanwhile stops the build at the next region, before anything is stored.

The tours are ray-cast in one 4 x 4 m room by two stands (one region each) with the noisy robot's declared
depth noise (sigma = 0.01 * depth^2) drawn into their depth."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from services.reconstructor.core import MapStore, ReconstructionConfig
from services.reconstructor.core.build_job import build_map
from services.reconstructor.service import FrameBuffer
from shared.jobs import Cancelled, JobContext
from shared.schemas import BuildMapRequest, CameraIntrinsics, Frame, MapBuildProgress, Pose, TourRecording
from tests.raycast import box_scene, cast_view

pytestmark = pytest.mark.timeout(120)

CAM = CameraIntrinsics(width_px=48, height_px=36, hfov_deg=90.0)
REL = 0.01
STANDS = {0: (1.2, 1.5), 1: (2.8, 2.5)}  # region -> where it stands
VIEWS = 8


def _room():
    return box_scene([((0, 0, -0.1), (4, 4, 0)), ((0, 0, 2.5), (4, 4, 2.6)), ((-0.1, 0, 0), (0, 4, 2.5)),
                      ((4, 0, 0), (4.1, 4, 2.5)), ((0, -0.1, 0), (4, 0, 2.5)), ((0, 4, 0), (4, 4.1, 2.5)),
                      ((1.8, 0.6, 0), (2.2, 1.0, 0.8))])  # floor, ceiling, walls and a box


def _frame(scene, rng, index: int, region: int, heading: float) -> Frame:
    pos = (*STANDS[region], 0.0)
    depth, _ = cast_view(scene, CAM, pos, heading)
    depth = np.maximum(depth + rng.normal(0.0, 1.0, depth.shape) * REL * depth**2, 0.0).astype(np.float32)
    rgb = np.full((CAM.height_px, CAM.width_px, 3), (90 + 20 * region, 120, 150), np.uint8)
    return Frame(index=index, timestamp_s=float(index), pose=Pose(position_m=pos, heading_rad=heading),
                 imu_heading_rad=heading, camera=CAM, rgb=rgb, depth_m=depth, depth_noise_rel=REL)


class _Events:
    """Where the job's events go (EventStream's ``emit``): kept in order; ``on`` runs on each progress."""

    def __init__(self, on=None):
        self.progress: list[MapBuildProgress] = []
        self.on = on

    def emit(self, kind, state, *, step=0, data=None, images=None):
        if isinstance(data, MapBuildProgress):
            self.progress.append(data)
            if self.on is not None:
                self.on(data)


def _run(tmp_path, events: _Events, cancel: threading.Event):
    scene, rng = _room(), np.random.default_rng(3)
    frames, recordings = FrameBuffer(64 << 20), []
    for region in STANDS:
        got = [_frame(scene, rng, i, region, 2 * np.pi * i / VIEWS) for i in range(VIEWS)]
        for f in got:
            frames.add(f"r{region}", f)
        recordings.append(TourRecording(exploration_id="e1", recording=f"r{region}", region=region,
                                        start_pose=got[0].pose, frame_count=len(got)))
    store = MapStore(tmp_path / "maps", fsync=False)
    req = BuildMapRequest(build_id="b1", exploration_id="e1", map_id="room", recordings=recordings,
                          reconstruction="rgbd")
    end = build_map(JobContext("b1", cancel, events), req, frames=frames, store=store,
                    config=ReconstructionConfig(backend="rgbd"), announce=lambda info: None, frames_timeout_s=1.0)
    return end, store


def test_the_build_reports_each_region_the_maps_volume_takes_in(tmp_path):
    events = _Events()
    end, store = _run(tmp_path, events, threading.Event())
    assert end.payload.info.point_count > 0
    assert store.load("room").details["fused_as_one_volume"] == [0, 1]
    stages = [p.stage for p in events.progress]
    assert stages == ["collecting"] * 3 + ["reconstructing"] * 2 + ["fusing"] * 2 + ["storing"]
    fusing = [p for p in events.progress if p.stage == "fusing"]
    assert [p.message for p in fusing] == ["map volume: 1 of 2 regions fused", "map volume: 2 of 2 regions fused"]
    shares = [p.progress for p in events.progress]
    assert shares == sorted(shares) and shares[-1] < 1.0  # never backwards


def test_a_cancel_while_the_map_is_fused_stops_at_the_next_region_and_stores_nothing(tmp_path):
    cancel = threading.Event()
    events = _Events(on=lambda p: cancel.set() if p.stage == "fusing" else None)
    with pytest.raises(Cancelled):
        _run(tmp_path, events, cancel)
    assert [p.stage for p in events.progress][-1] == "fusing"  # the second region's was not reported
    assert [p.stage for p in events.progress].count("fusing") == 1
    assert MapStore(tmp_path / "maps", fsync=False).list() == []
