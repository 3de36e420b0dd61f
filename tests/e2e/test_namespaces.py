"""Across hosts: the server and the robot in two network namespaces joined by a veth pair.

Host A (namespace ``ant-srv-*``, 10.200.K.1) runs what a deployment keeps on a server: the zenoh router
(listening on the veth address only), the gateway (HTTP on A's loopback only), the planner and - shared by
every robot once there are several (issue 17) - the mapper, renderer and reconstructor. Host B (``ant-bot-*``,
10.200.K.2) is the robot: robot-io alone, the only process that touches the robot. B reaches A only through
the router's one TCP port, as its own bus user with the password file copied over from A. From A, a whole
episode goes through the gateway's HTTP API with the evaluation runner's own steps (scene switch, curated
map upload, an oracle mission to its end), which is what a user with robots on other machines does.

Every process is a real one, started with ``ip netns exec``; namespaces (and the veth with them) and
processes are removed whatever happens. Skipped, with the reason, where namespaces cannot be made (not
root, no ``ip``, no permission in a container).
"""

from __future__ import annotations

import ctypes
import json
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from deploy.credentials import ensure_credentials
from deploy.launcher import free_port
from evaluation.dataset import SetSpec, generate_set
from evaluation.gateway_client import GatewayClient
from evaluation.runner import EvalRunner, MapSource, RunConfig

pytestmark = [pytest.mark.e2e, pytest.mark.system]
ROOT = Path(__file__).resolve().parents[2]
SERVER_SERVICES = ("planner", "mapper", "renderer", "reconstructor", "gateway")
ROBOT_SERVICES = ("robot_io",)
ROBOT = "robot0"
CLONE_NEWNET = 0x40000000
START_SCENE = "generated:3:area=50"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10, check=check)


class NetnsPair:
    """Two fresh namespaces and a veth pair between them (unique names per run, removed by :meth:`close`)."""

    def __init__(self):
        tag = secrets.token_hex(3)
        self.server, self.robot = f"ant-srv-{tag}", f"ant-bot-{tag}"
        self.server_if, self.robot_if = f"ants{tag}", f"antb{tag}"  # interface names: 15 characters at most
        octet = int(tag[:2], 16)
        self.server_ip, self.robot_ip = f"10.200.{octet}.1", f"10.200.{octet}.2"
        self.created: list[str] = []

    def open(self) -> None:
        for ns in (self.server, self.robot):
            _ip("netns", "add", ns)
            self.created.append(ns)
        _ip("link", "add", self.server_if, "netns", self.server, "type", "veth", "peer", "name", self.robot_if,
            "netns", self.robot)
        for ns, dev, addr in ((self.server, self.server_if, self.server_ip), (self.robot, self.robot_if, self.robot_ip)):
            _ip("-n", ns, "link", "set", "lo", "up")
            _ip("-n", ns, "addr", "add", f"{addr}/30", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")

    def close(self) -> None:
        for ns in reversed(self.created):  # the veth goes with its namespaces
            _ip("netns", "del", ns, check=False)
        self.created.clear()

    def counters(self, ns: str, dev: str) -> dict[str, int]:
        """The interface's byte counters, read inside its namespace (``ip netns exec`` mounts its sysfs)."""
        out = {}
        for what in ("rx_bytes", "tx_bytes"):
            r = subprocess.run(["ip", "netns", "exec", ns, "cat", f"/sys/class/net/{dev}/statistics/{what}"],
                               capture_output=True, text=True, timeout=10, check=True)
            out[what] = int(r.stdout)
        return out


def _in_netns(ns: str):
    """Thread initializer: this thread's sockets belong to ``ns`` (network namespaces are per thread)."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.open(f"/run/netns/{ns}", os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            raise OSError(ctypes.get_errno(), f"setns {ns}")
    finally:
        os.close(fd)


@pytest.fixture
def netns(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if shutil.which("ip") is None:
        pytest.skip("the `ip` tool (iproute2) is not installed")
    pair = NetnsPair()
    try:
        pair.open()
    except subprocess.CalledProcessError as exc:
        pair.close()
        pytest.skip(f"cannot create network namespaces here: {exc.stderr.strip() or exc}")
    yield pair
    pair.close()


class Host:
    """Processes started in one namespace (each in its own process group, stopped by :meth:`stop`)."""

    def __init__(self, ns: str, logs: Path):
        self.ns, self.logs = ns, logs
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, name: str, argv: list[str], env: dict[str, str]) -> subprocess.Popen:
        self.logs.mkdir(parents=True, exist_ok=True)
        with open(self.logs / f"{name}.log", "ab") as out:
            # `ip netns exec` execs the command: the pid is the service's own.
            p = subprocess.Popen(["ip", "netns", "exec", self.ns, *argv], env=env, cwd=ROOT, stdout=out,
                                 stderr=subprocess.STDOUT, start_new_session=True)
        self.procs[name] = p
        return p

    def stop(self, names: list[str] | None = None, timeout_s: float = 20.0) -> dict[str, int]:
        procs = {n: p for n, p in self.procs.items() if names is None or n in names}
        for p in procs.values():
            _signal_group(p, signal.SIGTERM)
        codes, end = {}, time.monotonic() + timeout_s
        for name, p in procs.items():
            try:
                codes[name] = p.wait(max(0.1, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                _signal_group(p, signal.SIGKILL)
                codes[name] = p.wait(5)
        return codes

    def log_tail(self, name: str, lines: int = 30) -> str:
        path = self.logs / f"{name}.log"
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:]) if path.is_file() else ""


def _signal_group(p: subprocess.Popen, sig: int) -> None:
    """Signal the process group this test started for ``p`` (its own session), if it still runs."""
    if p.poll() is None:
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            pass


def service_env(endpoint: str, service: str, password_file: Path | None, state: Path) -> dict[str, str]:
    """What host B (or A) sets to join the bus: the router's endpoint, client mode (the ACL holds only for
    traffic through the router), its own user and password file, a fixed instance name, the robot id."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ANT_", "ZENOH_"))}
    env.update({
        "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1",
        "ANT_ZENOH__CONNECT": json.dumps([endpoint]), "ANT_ZENOH__MULTICAST_SCOUTING": "false",
        "ANT_INSTANCE": f"{service.replace('_', '-')}-0", "ANT_ROBOT": ROBOT,
        "ANT_DB_PATH": str(state / "gateway.sqlite3"), "ANT_STORE_DIR": str(state / "maps"),
    })
    if password_file is not None:
        env.update({"ANT_ZENOH__MODE": "client", "ANT_ZENOH__USERNAME": service,
                    "ANT_ZENOH__PASSWORD_FILE": str(password_file)})
    return env


def test_router_gateway_planner_on_one_host_robot_on_another(netns, tmp_path):
    t0 = time.monotonic()
    port, http_port = 7447, free_port()  # the router's port is free: nothing else lives in a new namespace
    endpoint = f"tcp/{netns.server_ip}:{port}"
    server_dir, robot_dir = tmp_path / "host-a", tmp_path / "host-b"
    creds = server_dir / "zenoh"
    ensure_credentials(creds, listen=[endpoint], instances={"renderer": ["renderer-0"]})
    # Host B gets its own password file only (scp in real life), never the others'.
    (robot_dir / "zenoh").mkdir(parents=True)
    shutil.copy2(creds / "robot_io.password", robot_dir / "zenoh" / "robot_io.password")

    server, robot = Host(netns.server, server_dir / "logs"), Host(netns.robot, robot_dir / "logs")
    py = sys.executable
    on_a = on_b = None
    try:
        server.start("router", [py, "-m", "deploy.router", "--listen", endpoint, "--config",
                                str(creds / "router.json5")], service_env(endpoint, "router", None, server_dir))
        for name in SERVER_SERVICES:
            env = service_env(endpoint, name, creds / f"{name}.password", server_dir)
            if name == "gateway":
                env["ANT_PORT"] = str(http_port)
            server.start(name, [py, "-m", f"services.{name}"], env)
        for name in ROBOT_SERVICES:
            env = service_env(endpoint, name, robot_dir / "zenoh" / f"{name}.password", robot_dir)
            # robot-io starts in another small house (the default one costs seconds to build): the episode's
            # scene switch below stays a real one.
            env["ANT_ROBOT_CONFIG"] = json.dumps({"scene": START_SCENE})
            robot.start(name, [py, "-m", f"services.{name}"], env)

        # The episode (a generated house and its ground truth) is made while the services start; a small
        # house, as what crosses the veth does not depend on its size.
        ds, gt = generate_set(SetSpec(houses=1, per_house=1, floors=(1,), seed=7, area_m2=60.0), with_gt=True)
        assert ds.episodes[0].scene_id != START_SCENE
        url = f"http://127.0.0.1:{http_port}"
        on_a = ThreadPoolExecutor(max_workers=1, initializer=_in_netns, initargs=(netns.server,))
        on_b = ThreadPoolExecutor(max_workers=1, initializer=_in_netns, initargs=(netns.robot,))
        status = on_a.submit(_wait_all_alive, url, 120.0, server, robot).result()
        services = {s["service"]: s for s in status["services"]}
        assert set(services) >= {*SERVER_SERVICES, *ROBOT_SERVICES}, status
        t_up = time.monotonic() - t0
        # robot-io runs on host B (its own network namespace), nowhere else.
        robot_pid = robot.procs["robot_io"].pid
        assert os.stat(f"/proc/{robot_pid}/ns/net").st_ino == os.stat(f"/run/netns/{netns.robot}").st_ino
        assert os.stat(f"/proc/{robot_pid}/ns/net").st_ino != os.stat(f"/proc/{os.getpid()}/ns/net").st_ino
        # Two hosts, not one: A's gateway (on A's loopback) is not there from B, A's router is, over the veth.
        assert on_b.submit(_tcp_open, "127.0.0.1", http_port).result() is False
        assert on_b.submit(_tcp_open, netns.server_ip, port).result() is True
        before = netns.counters(netns.robot, netns.robot_if)

        # From host A, through A's gateway: switch robot-io's scene, upload the scene's curated cloud, run an
        # oracle mission to its end (the runner's own steps, called from a thread inside A's namespace).
        summary, r = on_a.submit(_episode, url, ds.episodes[0], gt["1"], tmp_path / "run").result()
        assert summary.scene == ds.episodes[0].scene_id and summary.reachable_area_m2 > 20
        assert r.status == "done", r.reason
        assert r.state in ("succeeded", "failed") and r.metrics is not None  # the mission ended
        assert len(r.trajectory_m) >= 2 and r.decisions  # the robot moved, step by step
        after = netns.counters(netns.robot, netns.robot_if)
        # The robot's side of the episode (scene summary, observations, poses) left B over the veth and the
        # commands came in: far more than the bus's keep-alives over the same time (a few hundred bytes/s).
        assert after["tx_bytes"] - before["tx_bytes"] > 20_000, (before, after)
        assert after["rx_bytes"] - before["rx_bytes"] > 5_000, (before, after)
        print(f"namespaces: system up in {t_up:.1f} s, episode in {time.monotonic() - t0 - t_up:.1f} s; "
              f"robot -> server {(after['tx_bytes'] - before['tx_bytes']) / 1e3:.0f} kB, server -> robot "
              f"{(after['rx_bytes'] - before['rx_bytes']) / 1e3:.0f} kB; "
              f"mission {r.state}, {len(r.decisions)} steps, {r.wall_s:.1f} s, stages {r.stage_s}")
        for p in list(server.procs.values()) + list(robot.procs.values()):
            assert p.poll() is None, f"a process died: {p.args}"
    finally:
        for pool in (on_a, on_b):
            if pool is not None:
                pool.shutdown(wait=False, cancel_futures=True)
        # As the launcher does: the robot, then the services, the router last (goodbyes still reach peers).
        codes = {**robot.stop(), **server.stop(list(SERVER_SERVICES)), **server.stop(["router"])}
    assert all(c == 0 for c in codes.values()), f"exit codes {codes}; logs in {tmp_path}"


def _tcp_open(host: str, port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(2.0)
        return sock.connect_ex((host, port)) == 0


def _episode(url: str, episode, gt, out: Path):
    with GatewayClient.connect(url, timeout_s=60) as gateway:
        summary = gateway.load_scene(episode.scene_id)  # POST /robot/scene: robot-io answers across the veth
        # A sparse curated cloud (a tenth of the runner's default density) keeps the upload and renders short.
        cfg = RunConfig(policy="oracle", map_source=MapSource.CURATED, max_steps=4, curated_density_per_m2=30,
                        mission_timeout_s=120, poll_s=0.2)
        runner = EvalRunner(gateway, gateway, cfg, out, progress=False)
        map_id = runner.ensure_map(episode.scene_id, episode.scene_id)
        return summary, runner.run_episode(episode, map_id, gt)


def _wait_all_alive(url: str, deadline_s: float, *hosts: Host) -> dict:
    """``GET /status`` from host A until every service, robot-io across the veth included, is alive."""
    end, last = time.monotonic() + deadline_s, None
    with httpx.Client(base_url=url, timeout=5) as http:
        while time.monotonic() < end:
            for host in hosts:
                for name, p in host.procs.items():
                    if p.poll() is not None:
                        raise AssertionError(f"{name} exited with {p.returncode}:\n{host.log_tail(name)}")
            try:
                last = http.get("/status").json()
                if last.get("all_alive") and {s["service"] for s in last["services"]} >= {*SERVER_SERVICES,
                                                                                          *ROBOT_SERVICES}:
                    return last
            except (httpx.HTTPError, ValueError):
                pass
            time.sleep(0.5)
    raise AssertionError(f"not every service alive after {deadline_s:.0f} s: {last}\n"
                         + "\n".join(h.log_tail(n, 5) for h in hosts for n in h.procs))
