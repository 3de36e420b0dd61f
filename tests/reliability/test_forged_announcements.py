"""A forged map announcement (issue 15, item 2): anyone on the bus can publish a MapInfo on
``ant/maps/<map>/updated``. The renderer checks an announced version against the store and never
drops the good version for an unverified one; a real new version is still picked up."""

from __future__ import annotations

from shared import keys
from shared.schemas import CameraIntrinsics, MapImportRequest, MapInfo, MapRequest, RenderRequest, RenderResult, ViewPose
from tests.reliability.conftest import scene_ply
from tests.reliability.live import LIVE_MAP
from tests.waiting import wait_until


def render_latest(live) -> RenderResult:
    info = live.typed.request(keys.MAP_INFO.format(map=LIVE_MAP), MapRequest(map_id=LIVE_MAP), MapInfo, timeout_s=20)
    centre = tuple((a + b) / 2 for a, b in zip(info.bounds_min_m, info.bounds_max_m))
    return live.typed.request(keys.RENDER_VIEWS.format(), RenderRequest(
        map_id=LIVE_MAP, views=[ViewPose(position_m=(centre[0], centre[1], info.bounds_min_m[2]))],
        camera=CameraIntrinsics(width_px=32, height_px=32)), RenderResult, timeout_s=30)


def forge(live, version: int, points: int = 5) -> None:
    live.typed.publish(keys.MAP_UPDATED.format(map=LIVE_MAP), MapInfo(
        map_id=LIVE_MAP, version=version, point_count=points, bounds_min_m=(0, 0, 0), bounds_max_m=(1, 1, 1)))


def test_a_forged_announcement_never_replaces_the_stored_version(live, tally):
    good = render_latest(live).version
    for version in (999, good + 1, 2**31 - 1, good):
        forge(live, version)
        tally.add("forged_announcements")
        # Every later render of "latest" still uses a version the store holds.
        for _ in range(3):
            assert render_latest(live).version == good
        tally.add("forged_announcements_ignored")


def test_a_real_new_version_is_still_picked_up_after_forgeries(live):
    good = render_latest(live).version
    forge(live, 999)
    info = live.typed.request(keys.MAP_IMPORT.format(map=LIVE_MAP), MapImportRequest(
        map_id=LIVE_MAP, filename="scene.ply", data=scene_ply(density_per_m2=10.0)), MapInfo, timeout_s=60)
    assert info.version == good + 1
    wait_until(lambda: render_latest(live).version == info.version, 20, "the renderer moved to the new version")
    forge(live, 999)
    assert render_latest(live).version == info.version
