"""bench.anticipation --ladder --noise-seeds (issue 33): each noise seed is a map of its own (its name, its
recording, its side record), the ladder's targets are checked on the seeds' means, and a corrected build's
time is compared with the uncorrected one's from the same recording. No real map is built here: the
exploration and the reconstructor are stand-ins, the simulated robot is real."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from bench import agent_maps
from bench import anticipation as an
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

    class Seen(list):  # the seeds explored, in order; .configs: each build's ReconstructionConfig
        configs: list

    seen = Seen()
    configs: list = []

    def discover(robot, config):
        seen.append(robot.config.noise.seed)
        return SimpleNamespace(tours=[], scene=None)

    class Reconstructor:
        def __init__(self, config):
            configs.append(config)

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
    seen.configs = configs
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


def test_a_named_build_sets_the_reconstructors_fields_and_voxels_is_a_map_of_its_own(stand_ins):
    from services.reconstructor.core import ReconstructionConfig

    for corr in ("off", "off+voxels", "none"):
        robot, _ = agent_maps.build_map(SCENE, "rgbd", "noisy", correction=corr)
        robot.close()
    off, voxels, none = stand_ins.configs
    assert stand_ins == [0]  # one recording: the fusion is the build's, not the exploration's
    assert off.backend_config == {} and voxels.backend_config == {"fusion": "voxels"}
    assert voxels.registration == off.registration and not off.registration.frames.enabled
    assert off.registration.stands.enabled and not none.registration.stands.enabled
    # Every entry is a set of ReconstructionConfig fields that it accepts.
    for name, fields in agent_maps.CORRECTIONS.items():
        ReconstructionConfig(backend="rgbd", **fields)
    names = {agent_maps._map_path(SCENE, "rgbd", "noisy", 128, 1.0, c)[0].name for c in ("off", "off+voxels")}
    assert names == {"generated_3_area-50_rgbd_noisy_corr-off_128.ply",
                     "generated_3_area-50_rgbd_noisy_corr-off-voxels_128.ply"}


def _scores(mapped: float, ssim: float, n: int = 3, label: float = 0.95, leak: float = 0.0) -> an.Scores:
    s = an.Scores()
    s.coverage, s.ssim, s.label, s.leak = [mapped] * n, [ssim] * n, [label] * n, [leak] * n
    s.holes = [0.0] * n
    return s


def _row(label, seed, corr, ssim_near, build_s=40.0, recording="r"):
    bands = {"< 1 m": _scores(0.95, ssim_near), "1-2 m": _scores(0.9, 0.88, 5, leak=0.001), "> 2 m": an.Scores()}
    record = {"build_s": build_s, "register_s": build_s / 4, "recording_id": recording}
    return an.LadderRow(label, seed, corr, bands, record, 100)


def test_the_seeds_mean_and_spread_per_band_and_a_band_with_no_view_is_left_out():
    rows = [_row("1x", s, "off", v) for s, v in ((0, 0.90), (1, 0.80), (2, 0.84))]
    (key, bands), = an.over_seeds(rows).items()
    assert key == ("1x", "off") and list(bands) == ["< 1 m", "1-2 m"]
    near = bands["< 1 m"]
    assert near.mean[1] == pytest.approx(2.54 / 3) and (near.lo[1], near.hi[1]) == pytest.approx((0.80, 0.90))
    assert near.mean[0] == pytest.approx(0.95) and near.per_seed.shape == (3, 4)
    rows[1].bands["< 1 m"].label = []  # no view of seed 1 scored labels: the mean says so, not the others' mean
    assert math.isnan(an.over_seeds(rows)[("1x", "off")]["< 1 m"].mean[2])


def test_targets_are_checked_on_the_seeds_means_not_on_one_seed(capsys):
    exact = _row("exact", None, "off", 0.90)
    # Seed 0 alone meets SSIM within 0.05 of the noise-free 0.90 (0.88); the seeds' mean (0.84) does not.
    noisy = [_row("1x", s, "off", v) for s, v in ((0, 0.88), (1, 0.80), (2, 0.84))]
    an._ladder_report("h", "visibility", 24, 0.03, [exact, noisy[0]], [0])
    one = capsys.readouterr().out
    an._ladder_report("h", "visibility", 24, 0.03, [exact, *noisy], [0, 1, 2])
    three = capsys.readouterr().out
    assert "targets 1x off             < 1 m  mapped>=85% +  SSIM-0.05 +" in one
    assert "targets 1x off             < 1 m  mapped>=85% +  SSIM-0.05 -" in three
    # One seed, the simulator's: rows unlabelled by seed, no table of means (the table as before seeds).
    assert "mean over noise seeds" not in one and "1x     off " in one and " s0 " not in one
    assert "mean over noise seeds 0 1 2" in three and "1x s1  off " in three
    assert "0.840 (0.800-0.880)" in three  # the < 1 m SSIM: mean (min-max)
    for out in (one, three):  # the verdict lines come last, the table's order unchanged
        assert out.rstrip().splitlines()[-1].startswith("targets 1x off             1-2 m")


def test_build_times_are_paired_only_from_one_recording_and_averaged_over_seeds(capsys):
    rows = [_row("exact", None, "off", 0.9, 30.0, "e"), _row("exact", None, "frames+regions", 0.9, 33.0, "e")]
    for s in (0, 1, 2):
        rows += [_row("1x", s, "off", 0.9, 40.0, f"r{s}"),
                 _row("1x", s, "frames+regions", 0.9, 60.0 + 10 * s, f"r{s}" if s else "other"),
                 _row("1x", s, "off:route", 0.9, 50.0, f"r{s}")]  # an oracle row: no build of the ladder
    pairs = an.build_pairs(rows)
    assert pairs[("exact", "frames+regions")] == [(None, 33.0, 30.0, 8.25, 7.5, True)]
    assert [(p.noise_seed, p.corrected_s, p.uncorrected_s, p.paired) for p in pairs[("1x", "frames+regions")]] == [
        (0, 60.0, 40.0, False), (1, 70.0, 40.0, True), (2, 80.0, 40.0, True)]
    assert set(pairs) == {("exact", "frames+regions"), ("1x", "frames+regions")}
    an._build_time_report(rows)
    out = capsys.readouterr().out
    assert "seed 0 60.0 / 40.0 s = 1.50x (registration 15.0 / 10.0 s) not from one recording" in out
    assert "mean 1.88x  <=2x +" in out  # (1.75 + 2.0) / 2: seed 0's pair is not one recording's
    rows[-2].record["build_s"] = 100.0
    an._build_time_report(rows)
    assert "mean 2.12x  <=2x -" in capsys.readouterr().out


def test_the_ladder_takes_distinct_non_negative_seeds_and_defaults_to_the_simulators(monkeypatch):
    got = {}
    monkeypatch.setattr(an, "ladder", lambda *a, **kw: got.update(kw))
    an.main(["--ladder"])
    assert got["noise_seeds"] == [agent_maps.NOISE_SEED]
    an.main(["--ladder", "--noise-seeds", "0", "1", "2"])
    assert got["noise_seeds"] == [0, 1, 2]
    for bad in (["1", "1"], ["-1"]):
        with pytest.raises(SystemExit):
            an.main(["--ladder", "--noise-seeds", *bad])


def test_with_a_build_without_any_registration_the_others_are_set_against_it(capsys):
    """"off" still registers the stands; where the ladder also built "none" (no registration at all), that
    is the uncorrected build the corrected ones' times are set against, "off" among them."""
    rows = [_row("1x", 0, "none", 0.9, 30.0, "r"), _row("1x", 0, "off", 0.9, 40.0, "r"),
            _row("1x", 0, "frames+regions", 0.9, 90.0, "r")]
    pairs = an.build_pairs(rows)
    assert set(pairs) == {("1x", "off"), ("1x", "frames+regions")}
    assert [(p.corrected_s, p.uncorrected_s) for p in pairs[("1x", "off")]] == [(40.0, 30.0)]
    an._build_time_report(rows)
    out = capsys.readouterr().out
    assert "build time 1x off / none: seed 0 40.0 / 30.0 s = 1.33x" in out and "mean 1.33x  <=2x +" in out
    assert "build time 1x frames+regions / none:" in out and "mean 3.00x  <=2x -" in out
    assert an.CORRECTIONS["none"]["registration"]["stands"] == {"enabled": False}
