"""bench.mapper --noise: the same house explored noise-free and with the robot's sensor noise, side by side."""

from __future__ import annotations

from bench import mapper
from services.robot_io.core import robot as robot_mod


def test_a_noisy_exploration_runs_on_a_robot_with_that_noise(monkeypatch):
    made = []
    create = robot_mod.ROBOTS.create

    def spy(name, cfg):
        made.append(cfg)
        return create(name, cfg)

    monkeypatch.setattr(robot_mod.ROBOTS, "create", spy)
    clean = mapper.run_scene("generated:0:area=40", 64, 1.5)
    noisy = mapper.run_scene("generated:0:area=40", 64, 1.5, noise="noisy", noise_seed=2)
    assert "noise" not in made[0] and made[1]["noise"]["seed"] == 2
    assert made[1]["noise"]["depth_noise_rel"] > 0 and made[1]["noise"]["odometry_drift_per_m"] > 0
    assert (clean["noise"], clean["noise_seed"]) == ("none", None)
    assert (noisy["noise"], noisy["noise_seed"]) == ("noisy", 2)
    for row in (clean, noisy):
        assert row["floors_reached"] == 1 and 0.9 <= row["coverage_visited_1.5m"] <= 1.0


def _row(noise, seed, floors, coverage):
    return {"scene": "generated:9:floors=2", "noise": noise, "noise_seed": seed, "floors_reached": floors,
            "scene_floors": 2, "coverage_visited_1.5m": coverage, "coverage_per_floor": [coverage, coverage],
            "steps": 10, "regions": 3, "finished": True}


def test_the_noise_table_names_the_seeds_that_lost_a_floor(capsys):
    mapper.print_noise_table([_row("none", None, 2, 0.99), _row("noisy", 0, 1, 0.487), _row("noisy", 1, 2, 0.98)],
                             1.5)
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == ("mapper noise generated:9:floors=2: coverage 99.0% noise-free, 48.7 / 98.0% noisy; "
                    "seeds short of a floor: [0]")
