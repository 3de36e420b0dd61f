"""The launcher's plan for a fleet: a robot-io and a gateway per robot, every other service shared."""

from __future__ import annotations

import json

import pytest

from deploy.launcher import PER_ROBOT, SERVICES, Launcher
from services.mapper.service import MapperSettings
from services.planner.service import PlannerSettings
from shared import keys


def test_three_robots_get_their_own_robot_io_and_gateway(tmp_path):
    lc = Launcher(tmp_path, robots=3, scenes=["generated:0", "generated:1", "generated:2"])
    assert lc.expected_instances() == {s: 3 if s in PER_ROBOT else 1 for s in SERVICES}
    ios = lc._service_procs("robot_io")
    assert [name for name, _ in ios] == ["robot_io-0", "robot_io-1", "robot_io-2"]
    assert [env["ANT_ROBOT"] for _, env in ios] == ["robot0", "robot1", "robot2"]
    assert [json.loads(env["ANT_ROBOT_CONFIG"])["scene"] for _, env in ios] == ["generated:0", "generated:1",
                                                                                "generated:2"]
    gws = lc._service_procs("gateway")
    assert [env["ANT_ROBOT"] for _, env in gws] == ["robot0", "robot1", "robot2"]
    assert len({env["ANT_PORT"] for _, env in gws}) == 3 and len(set(lc.gateway_urls)) == 3
    assert len({env["ANT_DB_PATH"] for _, env in gws}) == 3  # one database per gateway
    assert [name for name, _ in lc._service_procs("planner")] == ["planner-0"]  # shared: serves every robot
    assert "ANT_SERVE_ROBOTS" not in lc._service_procs("planner")[0][1]
    assert lc._service_procs("renderer")[0][1]["ANT_CACHE_MAPS"] == "4"


def test_planner_and_mapper_replicas_split_the_robots(tmp_path, monkeypatch):
    lc = Launcher(tmp_path, robots=5, replicas={"planner": 2, "mapper": 2})
    for name, settings in (("planner", PlannerSettings), ("mapper", MapperSettings)):
        plans = lc._service_procs(name)
        split = [json.loads(env["ANT_SERVE_ROBOTS"]) for _, env in plans]
        assert split == [["robot0", "robot2", "robot4"], ["robot1", "robot3"]]
        # ... and the service reads it as its robots (the same variable a deployment sets by hand).
        monkeypatch.setenv("ANT_SERVE_ROBOTS", plans[1][1]["ANT_SERVE_ROBOTS"])
        s = settings()
        assert s.serve_robots == ["robot1", "robot3"]
        assert keys.robot_routes(keys.MISSION_SUBMIT, s.serve_robots) == [
            "ant/robot1/planner/missions/submit", "ant/robot3/planner/missions/submit"]


def test_one_robot_keeps_the_names_it_always_had(tmp_path):
    lc = Launcher(tmp_path)
    (name, env), = lc._service_procs("gateway")
    assert name == "gateway-0" and env["ANT_ROBOT"] == "robot0" and env["ANT_DB_PATH"].endswith("gateway.sqlite3")
    assert lc.gateway_urls == [lc.gateway_url]


def test_bad_robot_ids_and_keys_are_refused(monkeypatch):
    with pytest.raises(ValueError):
        PlannerSettings(serve_robots=["robot*"])
    assert keys.robot_of(keys.MISSION_SUBMIT, "ant/robot7/planner/missions/submit") == "robot7"
    assert keys.robot_of(keys.MAPPER_PREDICT, "ant/robot7/mapper/predict/@map-0") == "robot7"  # instance route
    for bad in ("ant/*/planner/missions/submit", "ant/**/planner/missions/submit", "ant/robot7/mapper/predict"):
        with pytest.raises(keys.KeyExprError):
            keys.robot_of(keys.MISSION_SUBMIT, bad)
    assert keys.robot_routes(keys.MAPPER_PREDICT) == ["ant/*/mapper/predict"]


def test_renderer_replicas_share_requests_instead_of_splitting_robots(tmp_path):
    """``--replica renderer=2``: two renderers, each with its own instance name (its instance route
    ``<key>/@renderer-K``, which the router's ACL must allow), and no robot split: the renderer is not
    robot-scoped, any replica answers any robot's request (round-robin, one answer per request)."""
    lc = Launcher(tmp_path, robots=4, replicas={"renderer": 2})
    plans = lc._service_procs("renderer")
    assert [name for name, _ in plans] == ["renderer-0", "renderer-1"]
    assert [env["ANT_INSTANCE"] for _, env in plans] == ["renderer-0", "renderer-1"]
    assert all("ANT_SERVE_ROBOTS" not in env and env["ANT_CACHE_MAPS"] == "4" for _, env in plans)
    assert lc.expected_instances()["renderer"] == 2
    lc._router_argv("python")  # writes the credentials and the router's ACL for these instances
    conf = (tmp_path / "zenoh" / "router.json5").read_text()
    for instance in ("renderer-0", "renderer-1"):
        assert keys.routed(keys.RENDER_VIEWS.format(), instance) in conf
        assert keys.routed(keys.RENDER_MAP.format(), instance) in conf
