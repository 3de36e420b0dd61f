"""``make demo ROBOT=ros2 ROS2_DRIFT=1``: the stand-in's odometry drifts, and the demo says how the map
was corrected (issue 33)."""

from __future__ import annotations

import pytest

from deploy.demo import ROS2_DRIFT, drift_phrase, main, ros2_standin_config
from services.robot_io.core.ros2.standin import StandInConfig
from shared.schemas import DriftCorrection, PoseGraphSummary


def test_drift_makes_the_stand_ins_odometry_drift_under_its_own_config():
    cfg = ros2_standin_config('{"camera_rate_hz": 4}', True, 3)
    assert cfg == {"camera_rate_hz": 4, "noise": {"seed": 3, **ROS2_DRIFT}}
    noise = StandInConfig.model_validate({**cfg, "scene": "generated:0"}).noise  # the stand-in takes it
    assert noise.odometry_drift_per_m == 0.01 and noise.heading_drift_per_rad == 0.005
    # Noise given in the JSON wins over the flag's; without the flag the config is as given.
    given = ros2_standin_config('{"noise": {"odometry_drift_per_m": 0.1}}', True, 3)["noise"]
    assert given["odometry_drift_per_m"] == 0.1 and given["heading_drift_per_rad"] == 0.005
    assert ros2_standin_config('{"camera_rate_hz": 4}', False, 3) == {"camera_rate_hz": 4}


def test_the_backend_declares_the_depth_noise_the_stand_in_adds():
    """A stand-in whose camera is noisy is driven through a profile that says so (the generic one says 0),
    so the frames and panoramas carry it (the reconstructor's denoising, the tours' nearer looks)."""
    import json

    from deploy.launcher import StandIn
    from libs.ros2.profiles import profile

    def declared(standin: StandIn) -> float:
        cfg = json.loads(standin.robot_env("tcp/127.0.0.1:7447")["ANT_ROBOT_CONFIG"])
        return profile(cfg["profile"], cfg["profile_overrides"]).depth_noise_rel

    noisy = StandIn(standin_config={"noise": {"seed": 1, "depth_noise_rel": 0.01, **ROS2_DRIFT}})
    assert declared(noisy) == 0.01
    assert declared(StandIn(standin_config=ros2_standin_config("{}", True, 3))) == 0.0  # drift alone: exact depth
    assert declared(StandIn()) == 0.0


def test_drift_is_refused_without_the_ros2_stand_in():
    with pytest.raises(SystemExit):
        main(["--drift"])


def test_the_drift_line_names_the_mappers_corrections_and_the_registrations():
    d = DriftCorrection(applied=True, regions_corrected=1, max_correction_m=0.02, max_correction_deg=0.5,
                        odom_regions_corrected=3, odom_median_correction_m=0.041, odom_max_correction_m=0.12,
                        odom_max_correction_deg=1.4).model_dump(mode="json")
    line = drift_phrase(d)
    assert "3 of the tours moved by the mapper's localiser (median 0.041 m, max 0.120 m, 1.4 deg)" in line
    assert "registration moved 1 regions (max 0.020 m" in line
    assert "no tour moved" in drift_phrase({**d, "odom_regions_corrected": 0})
    assert "pose graph" not in line
    g = PoseGraphSummary(panoramas=160, scan_edges=500, loop_closures_accepted=440, loop_closures_rejected=2,
                         applied=True, panoramas_corrected=120).model_dump(mode="json")
    assert "the pose graph placed 120 of 160 panoramas (440 loop closures, 2 rejected)" in drift_phrase(
        {**d, "pose_graph": g})
    assert "graph nodes" not in drift_phrase({**d, "pose_graph": g})
    moved = {**g, "nodes_moved": 37, "median_node_shift_m": 0.024, "max_node_shift_m": 0.081}
    assert ("(440 loop closures, 2 rejected) and moved 37 exploration graph nodes with them (median 0.024 m, "
            "max 0.081 m)") in drift_phrase({**d, "pose_graph": moved})
    assert "none applied" in drift_phrase(DriftCorrection().model_dump(mode="json"))
    assert "none applied" in drift_phrase(None)
