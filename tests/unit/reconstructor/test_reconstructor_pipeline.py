"""End to end on a real generated house: explore -> tours -> reconstruct -> align -> integrate -> store."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.reconstructor.core import (
    AlignmentConfig,
    MapStore,
    ReconstructionConfig,
    Reconstructor,
    region_from_recording,
)
from shared.cloud import PointCloud, view_dirs_unit


@pytest.fixture(scope="module")
def rgbd_build(house):
    with Reconstructor(ReconstructionConfig(backend="rgbd")) as r:
        return r.build_from_recordings(house.recordings, house.label_names)


@pytest.fixture(scope="module")
def mono_build(house):
    cfg = ReconstructionConfig(backend="mono-sim", backend_config={"seed": 7})
    with Reconstructor(cfg) as r:
        return r.build_from_recordings(house.recordings, house.label_names)


def test_rgbd_map_lies_on_the_scene_mesh(house, rgbd_build):
    b = rgbd_build
    assert len(b.regions) == len(house.recordings)
    dist = house.mesh_distance(b.cloud.xyz)
    # Perfect simulated depth: points sit on the surfaces up to the voxel centroid offset.
    assert dist.mean() < 0.01 and np.percentile(dist, 95) < 0.02
    # The map covers the house: its footprint reaches most of the reachable floor.
    nav = house.robot.nav
    reach = nav.nodes_m[nav.component == nav.main_component]
    from scipy.spatial import cKDTree

    d, _ = cKDTree(b.cloud.xyz[:, :2]).query(reach[:, :2])
    assert (d < 0.1).mean() > 0.9


def test_rgbd_alignment_is_identity_and_measures_delta_near_one(rgbd_build):
    for rep in rgbd_build.regions:
        a = rep.alignment
        assert rep.metric and a.delta_applied == 1.0
        # The metric cloud rendered at its origin must look like the start frame and measure scale 1.
        assert abs(a.delta_mean - 1.0) < 0.03 and abs(a.delta_median - 1.0) < 0.03
        assert abs(math.degrees(a.theta_t_rad)) < 1.0 and a.theta_applied_rad == 0.0
        assert a.ssim > 0.3 and a.valid_fraction > 0.05


def test_rgbd_keeps_semantic_labels(house, rgbd_build):
    c = rgbd_build.cloud
    assert c.labels is not None and c.label_names == house.label_names
    known = c.labels >= 0
    assert known.mean() > 0.95
    assert set(np.unique(c.labels[known])) <= set(house.label_names)
    # A floor label is on points at floor height, a ceiling-free map has most floors labelled "floor".
    floor_ids = [k for k, v in house.label_names.items() if v.endswith("floor")]
    on_floor = np.isin(c.labels, floor_ids)
    assert on_floor.any() and np.abs(c.xyz[on_floor, 2] - np.median(c.xyz[on_floor, 2])).max() < 0.3


def _view_units(cloud) -> np.ndarray:
    v = view_dirs_unit(cloud.view_dirs).astype(np.float64)
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)


def test_rgbd_map_knows_which_side_of_each_surface_was_seen(house, rgbd_build):
    c = rgbd_build.cloud
    assert c.view_dirs is not None
    u = _view_units(c)
    # A ray along a point's view direction runs back through the free space the camera looked
    # across; the opposite ray enters the wall (10 cm thick between rooms) or the floor and stops.
    forward = house.free_path_m(c.xyz + 0.03 * u, u)
    backward = house.free_path_m(c.xyz - 0.03 * u, -u)
    assert (forward > 0.2).mean() > 0.995
    assert (backward > 0.2).mean() < 0.2
    floor_ids = [k for k, v in house.label_names.items() if v.endswith("floor")]
    assert (u[np.isin(c.labels, floor_ids), 2] > 0).all()  # floors are seen from above


def test_mono_sim_is_grounded_to_metric_scale(house, mono_build):
    errors = [rep.scale_error for rep in mono_build.regions]
    scales = [rep.true_scale for rep in mono_build.regions]
    assert all(e is not None for e in errors)
    # The emulation really is off scale (else this test could not fail) ...
    assert max(abs(math.log(s)) for s in scales) > math.log(1.2)
    # ... and grounding recovers it: the target is a median within 2 %.
    assert np.median(errors) <= 0.02 and max(errors) <= 0.05
    dist = house.mesh_distance(mono_build.cloud.xyz)
    assert dist.mean() < 0.05 and np.percentile(dist, 95) < 0.15


def test_mono_sim_view_directions_are_grounded_with_the_points(mono_build, rgbd_build):
    # The emulation turns the cloud into its reference camera's frame and alignment turns it back:
    # the directions must follow both turns, and agree with the rgbd map's at the nearest point.
    from scipy.spatial import cKDTree

    mono, rgbd = mono_build.cloud, rgbd_build.cloud
    assert mono.view_dirs is not None
    _, nearest = cKDTree(rgbd.xyz).query(mono.xyz)
    dots = (_view_units(mono) * _view_units(rgbd)[nearest]).sum(axis=1)
    assert np.median(dots) > 0.98


def test_mono_sim_heading_comes_from_the_matched_frame(house):
    cfg = ReconstructionConfig(backend="mono-sim", backend_config={"seed": 7})
    with Reconstructor(cfg) as r:
        region = region_from_recording(house.recordings[0])
        regional = r.backend.reconstruct(region)
        rep = r.aligner.align(region, regional)
    assert rep.delta_applied != 1.0
    err = math.degrees(abs(math.remainder(rep.theta_applied_rad - regional.true_yaw_rad, 2 * math.pi)))
    assert err < 2.0


def test_never_using_the_matched_heading_breaks_mono_sim_when_the_reference_turned(house):
    # The counterfactual of the previous test: without theta_t, regions whose reference frame is
    # turned land rotated, far from the mesh.
    cfg = ReconstructionConfig(backend="mono-sim", backend_config={"seed": 7},
                               alignment=AlignmentConfig(use_matched_heading="never"))
    with Reconstructor(cfg) as r:
        b = r.build_from_recordings(house.recordings, house.label_names)
    turned = [k for k, rep in enumerate(b.regions) if abs(rep.alignment.theta_t_rad) > math.radians(10)]
    if not turned:
        pytest.skip("seed 7 picked unturned reference frames in this house")
    dist = house.mesh_distance(b.regional_clouds[turned[0]].xyz)
    assert dist.mean() > 0.1


def test_median_statistic_is_selectable(house):
    cfg = ReconstructionConfig(backend="mono-sim", alignment=AlignmentConfig(statistic="median"))
    with Reconstructor(cfg) as r:
        region = region_from_recording(house.recordings[0])
        rep = r.aligner.align(region, r.backend.reconstruct(region))
    assert rep.delta_applied == rep.delta_median != rep.delta_mean


def test_build_is_stored_and_reloads_identically(tmp_path, rgbd_build):
    store = MapStore(tmp_path, cache_maps=0)
    b = rgbd_build
    info = store.save("house", b.cloud, source="generated", regions=len(b.regions),
                      scale_factors=b.scale_factors, timings_s=b.timings_s, details=b.details())
    assert info.version == 1 and info.point_count == len(b.cloud) and info.has_labels
    m = store.load("house")
    assert np.array_equal(m.cloud.xyz, b.cloud.xyz)
    assert np.array_equal(m.cloud.rgb, b.cloud.rgb)
    assert np.array_equal(m.cloud.labels, b.cloud.labels)
    assert b.cloud.view_dirs is not None and np.array_equal(m.cloud.view_dirs, b.cloud.view_dirs)
    served = PointCloud.from_chunks(store.chunks("house", max_points=len(b.cloud) // 3 + 1))
    assert np.array_equal(served.view_dirs, b.cloud.view_dirs)
    assert m.cloud.label_names == b.cloud.label_names
    assert m.info.scale_factors == pytest.approx(b.scale_factors)
    assert [r["region"] for r in m.details["regions"]] == [r.region for r in b.regions]
    assert m.details["regions"][0]["alignment"]["matched_index"] == b.regions[0].alignment.matched_index


def test_a_metric_region_whose_alignment_check_cannot_run_is_still_integrated(house, monkeypatch):
    from services.reconstructor.core import AlignmentError, MetricAligner, ReconstructionConfig, Reconstructor

    def fail(self, region, regional):
        raise AlignmentError(f"region {region.region}: only 0.0% of the forward view has depth")

    monkeypatch.setattr(MetricAligner, "align", fail)
    with Reconstructor(ReconstructionConfig(backend="rgbd")) as r:
        b = r.build_from_recordings(house.recordings[:1], house.label_names)
    assert len(b.cloud) > 1000 and b.scale_factors == [1.0]
    assert "alignment check skipped" in b.regions[0].error
    # A non-metric (mono) cloud cannot be grounded without it: that stays an error.
    with Reconstructor(ReconstructionConfig(backend="mono-sim")) as r, pytest.raises(AlignmentError):
        r.build_from_recordings(house.recordings[:1], house.label_names)
