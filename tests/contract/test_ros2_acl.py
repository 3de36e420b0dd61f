"""The ROS 2 side on the authenticated bus: a real zenoh router with the generated ACL, the robot's ROS 2
side joining as ``ros2_robot`` (issue 15 item 4). It and robot-io share the ROS 2 key space of both key
styles (bridge: the ROS name; rmw_zenoh: ``<domain>/<name>/<type>/<hash>`` and ``@ros2_lv`` tokens); the
ROS side can neither publish, serve nor read anything under ``ant/**``, and other services cannot
reach the ROS 2 keys."""

from __future__ import annotations

import json

import pytest

from deploy.zenoh import acl
from libs.ros2 import messages as m
from libs.ros2.keys import EntityKind, Qos, RmwZenohKeys
from shared import keys
from shared.bus.zenoh_bus import ZenohBus
from tests.contract.conftest import Inbox, authenticated_router, wait_until

pytestmark = pytest.mark.contract

ROS2 = acl.Ros2Side()
USERS = ("robot_io", "gateway", "reconstructor", ROS2.user)
PASSWORDS = {u: f"pw-{u}" for u in (*acl.SERVICES, ROS2.user)}
RMW = RmwZenohKeys(domain_id=0)
ODOM_TYPE = m.RosType(m.MESSAGES["odometry"])


@pytest.fixture(scope="module")
def net(tmp_path_factory):
    with authenticated_router(tmp_path_factory.mktemp("ros2-acl"), PASSWORDS, ros2=ROS2) as router:
        clients = {u: router.connect(u) for u in USERS}
        yield {**clients, "endpoint": router.endpoint}
        for c in clients.values():
            c.close()


def _rmw_odom_key() -> str:
    return RMW.topic_key("/odom", ODOM_TYPE)


def test_the_ros2_side_and_robot_io_exchange_topics_in_both_key_styles(net):
    robot, ros = net["robot_io"], net[ROS2.user]
    odom_rmw = _rmw_odom_key()
    to_robot_io, to_ros = Inbox(), Inbox()
    subs = [robot.subscribe(k, to_robot_io) for k in ("odom", odom_rmw)]
    subs.append(ros.subscribe("cmd_vel", to_ros))
    wait_until(lambda: ros.publish("odom", b"o1") or to_robot_io.has("odom", b"o1"), what="bridge odom routed")
    wait_until(lambda: ros.publish(odom_rmw, b"o2") or to_robot_io.has(odom_rmw, b"o2"), what="rmw_zenoh odom")
    wait_until(lambda: robot.publish("cmd_vel", b"twist") or to_ros.has("cmd_vel", b"twist"), what="cmd_vel routed")
    for s in subs:
        s.close()


def test_robot_io_calls_a_ros2_service_and_sees_the_graph_tokens(net):
    robot, ros = net["robot_io"], net[ROS2.user]
    srv = ros.serve(["teleport"], lambda k, p: b"teleported")
    wait_until(lambda: [r.payload for r in robot.query("teleport", b"go", timeout_s=1.0) if r.ok] == [b"teleported"],
               what="the teleport service answered")
    token_key = RMW.entity_token("0123456789abcdef", 0, 1, EntityKind.PUBLISHER, "standin", "/odom", ODOM_TYPE, Qos())
    token = ros.liveliness_token(token_key)
    wait_until(lambda: token_key in robot.alive("@ros2_lv/0/**", timeout_s=1.0), what="graph token seen")
    token.close()
    srv.close()


def test_the_ros2_side_cannot_touch_the_services_keys(net):
    robot, gw, rec, ros = net["robot_io"], net["gateway"], net["reconstructor"], net[ROS2.user]
    # robot-io's frames, watched where the ACL lets them be read: by their consumer, the reconstructor.
    pose = keys.IO_FRAMES.format(robot="robot0", recording="t1")
    at_gw, at_ros = Inbox(), Inbox()
    sub_gw = rec.subscribe(keys.IO_FRAMES.pattern(), at_gw)
    sub_ros = ros.subscribe("ant/**", at_ros)
    hijack = ros.serve([keys.INFO.format(service="robot_io", instance="fake")], lambda k, p: b"hijacked")
    fake = ros.liveliness_token(keys.ALIVE.format(service="robot_io", instance="impostor"))
    wait_until(lambda: robot.publish(pose, b"ready") or at_gw.has(pose, b"ready"), what="frames routed to the reconstructor")
    # The forged sample first, then a genuine one: once the genuine one arrived the forged one would have too.
    ros.publish(pose, b"forged")
    ros.publish("odom", b"marker")  # same session, same router, in order
    robot.publish(pose, b"genuine")
    wait_until(lambda: at_gw.has(pose, b"genuine"), what="the genuine pose")
    assert not at_gw.has(pose, b"forged")
    # Its own forged sample reaches its own subscriber inside its session (zenoh's local delivery, no
    # router involved); nothing robot-io published under ant/** reaches it.
    assert [d for _, d in at_ros.got if d != b"forged"] == [], "the ROS side reads nothing of ant/**"
    answers = gw.query(keys.INFO.format(service="robot_io", instance="fake"), b"?", timeout_s=1.0)
    assert b"hijacked" not in [r.payload for r in answers if r.ok]
    assert all(not t.endswith("/impostor") for t in gw.alive(keys.ALIVE.pattern(), timeout_s=1.0))
    for c in (sub_gw, sub_ros, hijack, fake):
        c.close()


def test_other_services_cannot_reach_the_ros2_keys(net):
    gw, ros = net["gateway"], net[ROS2.user]
    at_ros = Inbox()
    sub = ros.subscribe("cmd_vel", at_ros)
    robot = net["robot_io"]
    gw.publish("cmd_vel", b"from-the-gateway")
    wait_until(lambda: robot.publish("cmd_vel", b"from-robot-io") or at_ros.has("cmd_vel", b"from-robot-io"),
               what="robot-io's cmd_vel")
    assert not at_ros.has("cmd_vel", b"from-the-gateway")
    sub.close()


def test_a_ros_name_under_the_services_root_is_refused():
    with pytest.raises(acl.AclError, match="overlap"):
        acl.ros2_key_exprs(acl.Ros2Side(names=("/ant/robot0/io/pose",)))
    with pytest.raises(acl.AclError, match="key style"):
        acl.ros2_key_exprs(acl.Ros2Side(styles=("dds",)))
    with pytest.raises(acl.AclError, match="domain"):
        acl.ros2_key_exprs(acl.Ros2Side(domain_id=233))


def test_the_stand_in_tool_joins_with_its_flags_or_the_environment(net, tmp_path, monkeypatch):
    import argparse

    from services.robot_io.tools.ros2_robot import bus_settings

    endpoint = net["endpoint"]
    pw = tmp_path / "ros2_robot.password"
    pw.write_text(PASSWORDS[ROS2.user] + "\n")
    flags = argparse.Namespace(connect=[endpoint], listen=[], mode=None, username=ROS2.user, password_file=str(pw))
    settings = bus_settings(flags)
    assert settings.mode == "client"
    ZenohBus(settings).close()  # admitted by the authenticated router
    monkeypatch.setenv("ANT_ZENOH__MODE", "client")
    monkeypatch.setenv("ANT_ZENOH__USERNAME", ROS2.user)
    monkeypatch.setenv("ANT_ZENOH__PASSWORD_FILE", str(pw))
    from_env = bus_settings(argparse.Namespace(connect=[endpoint], listen=[], mode=None, username=None,
                                               password_file=None))
    assert (from_env.mode, from_env.username, from_env.password_file) == ("client", ROS2.user, str(pw))
    ZenohBus(from_env).close()
    pw.write_text("wrong\n")
    with pytest.raises(Exception, match="(?i)unable to connect"):
        ZenohBus(from_env)


def test_the_launcher_keeps_auth_on_with_the_stand_in_and_gives_both_sides_their_users(tmp_path, monkeypatch):
    from deploy.launcher import Launcher, StandIn

    monkeypatch.delenv("ANT_BUS_AUTH", raising=False)
    launcher = Launcher(tmp_path, standin=StandIn(keys="rmw_zenoh"))
    assert launcher.auth
    argv = launcher._router_argv("python")
    router = (tmp_path / "zenoh" / "router.json5").read_text()
    assert '"ros2_robot"' in router and "@ros2_lv/0/**" in router
    assert '"cmd_vel"' not in router, "only the stand-in's key style is granted"
    assert argv[-1].endswith("router.json5")
    standin_env = launcher._env("ros2-robot", user=acl.Ros2Side.user)
    assert standin_env["ANT_ZENOH__USERNAME"] == "ros2_robot" and standin_env["ANT_ZENOH__MODE"] == "client"
    assert (tmp_path / "zenoh" / "ros2_robot.password").read_text().strip() == launcher.users["ros2_robot"]
    ((_, robot_io_env),) = launcher._service_procs("robot_io")
    transport = json.loads(robot_io_env["ANT_ROBOT_CONFIG"])["transport_config"]["zenoh"]
    assert transport["username"] == "robot_io" and transport["mode"] == "client"
    assert transport["password_file"] == str(tmp_path / "zenoh" / "robot_io.password")


def test_a_system_with_the_stand_in_refuses_to_run_its_bus_open(tmp_path, monkeypatch):
    from deploy.launcher import Launcher, StandIn

    monkeypatch.setenv("ANT_BUS_AUTH", "0")
    with pytest.raises(ValueError, match="never runs its bus open"):
        Launcher(tmp_path, standin=StandIn(keys="bridge"))
    with pytest.raises(ValueError, match="never runs its bus open"):
        Launcher(tmp_path, standin=StandIn(keys="bridge"), auth=False)
    assert not Launcher(tmp_path).auth  # without a robot's ROS 2 side the opt-out still stands
