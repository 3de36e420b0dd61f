"""bench.agent_maps' noise seeds (issue 33): each noise seed is a map of its own (its name, its recording,
its side record). No real map is built here: the exploration and the reconstructor are stand-ins, the
simulated robot is real."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from bench import agent_maps
from shared.cloud import PointCloud

SCENE = "generated:3:area=50"


def test_the_default_seed_is_the_simulators_and_keeps_every_maps_name():
    from services.robot_io.core.sensors import SensorNoiseConfig

    assert agent_maps.NOISE_SEED == SensorNoiseConfig.model_fields["seed"].default
    name = lambda *a, **kw: agent_maps._map_path(*a, **kw)[0].name  # noqa: E731
    # The names the cache held before seeds were named: a map of the default seed is the same file.
    assert name("generated:0", "rgbd", "noisy", 128, 1.0, "off") == "generated_0_rgbd_noisy_corr-off_128.ply"
    assert name("generated:0", "rgbd", "noisy", 128, 1.0, "off", noise_seed=0) == name("generated:0", "rgbd", "noisy",
                                                                                       128, 1.0, "off")
    assert (name("generated:3:floors=2", "rgbd", "noisy", 128, 2.0, "frames+regions", True, "route")
            == "generated_3_floors-2_rgbd_noisy_x2_corr-frames-regions_oracle_route_128.ply")
    assert name("generated:0", "rgbd", None) == "generated_0_rgbd_128.ply"
    seeded = {name("generated:0", "rgbd", "noisy", 128, 2.0, "off", noise_seed=s) for s in (0, 1, 2)}
    assert seeded == {"generated_0_rgbd_noisy_x2_corr-off_128.ply", "generated_0_rgbd_noisy_seed1_x2_corr-off_128.ply",
                      "generated_0_rgbd_noisy_seed2_x2_corr-off_128.ply"}


def test_a_noise_seed_reaches_the_simulator_and_is_refused_where_it_draws_nothing():
    assert agent_maps.noise_config("noisy", 2.0, 5)["seed"] == 5
    assert agent_maps.noise_config("noisy")["seed"] == agent_maps.NOISE_SEED
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError):
            agent_maps.noise_config("noisy", 1.0, bad)
    with pytest.raises(ValueError):  # a noise-free robot draws nothing: a second copy of the same map
        agent_maps.build_map(SCENE, "rgbd", None, noise_seed=1)


@pytest.fixture
def stand_ins(monkeypatch, tmp_path):
    """build_map with a stand-in exploration (counts explorations, notes the robot's noise seed) and
    reconstructor (a few points, a build time); the cache under tmp_path."""
    import services.mapper.core as mapper
    import services.reconstructor.core as reconstructor

    seen: list[int] = []

    def discover(robot, config):
        seen.append(robot.config.noise.seed)
        return SimpleNamespace(tours=[], scene=None)

    class Reconstructor:
        def __init__(self, config):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def build_from_recordings(self, recs, label_names):
            n = 5
            cloud = PointCloud(np.random.default_rng(len(seen)).uniform(0, 1, (n, 3)), np.zeros((n, 3), np.uint8),
                               view_dirs=np.zeros((n, 3), np.int8))
            summary = SimpleNamespace(model_dump=lambda mode: {"applied": False})
            return SimpleNamespace(cloud=cloud, regions=[], timings_s={"register_regions": 0.25},
                                   drift_summary=lambda: summary)

    monkeypatch.setattr(mapper, "discover", discover)
    monkeypatch.setattr(mapper, "discovery_config", lambda profile: None)
    monkeypatch.setattr(mapper, "execute_tours", lambda robot, tours, scene, rate_hz, on_skip: [])
    monkeypatch.setattr(reconstructor, "Reconstructor", Reconstructor)
    monkeypatch.setattr(agent_maps, "MAPS", tmp_path)
    monkeypatch.setattr(agent_maps, "_RECORDINGS", {})
    return seen


def test_each_seed_is_its_own_recording_and_map_and_its_corrections_share_one_recording(stand_ins):
    def build(seed: int, corr: str) -> dict:
        robot, _ = agent_maps.build_map(SCENE, "rgbd", "noisy", correction=corr, noise_seed=seed)
        robot.close()
        return agent_maps.build_record(SCENE, "rgbd", "noisy", 1.0, corr, noise_seed=seed)

    off1, corr1 = build(1, "off"), build(1, "frames+regions")
    assert stand_ins == [1]  # one exploration, by the seeded robot, served both builds
    assert off1["recording_id"] == corr1["recording_id"] and off1["noise_seed"] == corr1["noise_seed"] == 1
    assert off1["register_s"] == 0.25 and off1["build_s"] >= 0.0
    off2 = build(2, "off")  # the recording key holds the seed: seed 2 is explored anew, not served seed 1's
    assert stand_ins == [1, 2] and off2["noise_seed"] == 2 and off2["recording_id"] != off1["recording_id"]
    off0 = build(0, "off")
    assert stand_ins == [1, 2, 0] and agent_maps.build_record(SCENE, "rgbd", "noisy", 1.0, "off") == off0
    build(1, "off")  # cached by its own name: no exploration, the record as it was
    assert stand_ins == [1, 2, 0] and build(1, "off") == off1
    robot, _ = agent_maps.build_map(SCENE, "rgbd", None)
    robot.close()
    assert agent_maps.build_record(SCENE, "rgbd", None)["noise_seed"] is None
