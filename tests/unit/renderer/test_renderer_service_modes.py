"""One renderer service answers views in the splat mode a request asks for (the paper-vs-visibility
ablation runs both on one system), and says in the result which mode rendered them."""

from __future__ import annotations

import numpy as np
import pytest

from services.renderer.service import RendererService, RendererSettings
from shared.bus import FakeBus, FakeNetwork
from shared.bus.typed import TypedBus
from shared.clients import RendererClient
from shared.runner import RunningService
from shared.schemas import CameraIntrinsics, ViewPose
from tests.doubles.scripted_services import ScriptedReconstructor

CAM = CameraIntrinsics(width_px=64, height_px=64, hfov_deg=90.0)


@pytest.fixture(scope="module")
def renderer():
    net = FakeNetwork()
    store = ScriptedReconstructor(TypedBus(FakeBus(net)))
    # A wall 2 m ahead (x = 2), sampled on a 2 cm grid, in front of a second wall at x = 4.
    ys, zs = np.meshgrid(np.arange(-2.0, 2.0, 0.02), np.arange(0.0, 2.5, 0.02))
    near = np.stack([np.full(ys.size, 2.0), ys.ravel(), zs.ravel()], 1)
    far = near + [2.0, 0.0, 0.0]
    xyz = np.concatenate([near, far])
    rgb = np.concatenate([np.full((len(near), 3), 200), np.full((len(far), 3), 40)])
    store.add("walls", xyz, rgb)
    service = RunningService(RendererService(RendererSettings(instance="r-1")), FakeBus(net))
    yield RendererClient(TypedBus(FakeBus(net)), timeout_s=60.0)
    service.close()


def test_a_request_picks_the_splat_mode_and_the_result_names_it(renderer):
    view = [ViewPose(position_m=(0.0, 0.0, 0.0), heading_rad=0.0)]
    default = renderer.views("walls", view, CAM, with_labels=False)
    paper = renderer.views("walls", view, CAM, with_labels=False, splat_mode="paper")
    visibility = renderer.views("walls", view, CAM, with_labels=False, splat_mode="visibility")
    assert default.splat_mode == "visibility" and visibility.splat_mode == "visibility"
    assert paper.splat_mode == "paper"
    np.testing.assert_array_equal(default.depth_m, visibility.depth_m)
    # Both modes see the near wall, 2 m ahead, and not the far one behind it.
    for res in (paper, visibility):
        d = res.depth_m[0][res.depth_m[0] > 0]
        assert np.median(d) == pytest.approx(2.0, abs=0.05)
