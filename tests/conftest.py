"""Shared fixtures. Process-level tests need the colcon workspace (make setup)."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
INSTALL = REPO / "ros2_ws" / "install"
NODE_BIN = INSTALL / "artrack_nodes" / "lib" / "artrack_nodes"


def _private_domain() -> int:
    """A DDS domain (100-199) of this test process alone: under pytest-xdist (`make test` runs two
    workers, one test file each at a time) each worker draws from its own block of 25, so that the
    graphs two workers start at once never share a domain."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    index = int(worker[2:]) if worker[2:].isdigit() else 0
    return 100 + (25 * index + os.getpid() % 25) % 100


def ros_env(domain_id: int | None = None) -> dict[str, str]:
    """The environment of scripts/env.sh, with a private DDS domain for this test run."""
    out = subprocess.run(["bash", "-c", f". {REPO}/scripts/env.sh && env -0"], capture_output=True, check=True)
    env = dict(item.split("=", 1) for item in out.stdout.decode().split("\0") if "=" in item)
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    env["ROS_DOMAIN_ID"] = str(domain_id if domain_id is not None else _private_domain())
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return env


@pytest.fixture(scope="session")
def env() -> dict[str, str]:
    if not (NODE_BIN / "skeleton").is_file():
        pytest.fail("workspace not built: run `make setup` (ros2_ws/install is missing)")
    return ros_env()


def run_artrack(env: dict[str, str], *args: str, timeout: float = 600, check: bool = True):
    """Run the installed `artrack` command; returns the CompletedProcess."""
    exe = NODE_BIN / "artrack"
    proc = subprocess.run([str(exe), *args], env=env, capture_output=True, text=True, timeout=timeout, cwd=REPO)
    if check and proc.returncode != 0:
        raise AssertionError(f"artrack {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return proc


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory, env) -> Path:
    """A 2.5 s, 4-camera, 320x240 synthetic scene shared by the process-level tests (75 frames;
    the blob trackers start after the background seed, about 1.7 s)."""
    out = tmp_path_factory.mktemp("scene") / "small.mcap"
    run_artrack(env, "synth", "--seed", "3", "--out", str(out), "--duration", "2.5", "--width", "320",
                "--height", "240", "--quiet")
    return out



@pytest.fixture
def probe(env):
    """(node, executor): an rclpy participant of the test process on the test run's private domain
    (rclpy imported here only: the core tests run without it)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    context = Context()
    rclpy.init(context=context, domain_id=int(env["ROS_DOMAIN_ID"]))
    node = Node("test_probe", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=context)


def spin_until(executor, predicate, timeout_s: float, step_s: float = 0.05) -> bool:
    """Spin ``executor`` until ``predicate()`` holds (True) or ``timeout_s`` passed (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        executor.spin_once(timeout_sec=step_s)
        if predicate():
            return True
    return False


def call_service(executor, client, request, timeout_s: float = 30.0, attempts: int = 3):
    """Call an idempotent service over DDS and return its response (None if none came in ``timeout_s``).

    Fast DDS can drop a response sent before the server has matched the client's response reader,
    even after ``service_is_ready()`` (ros2/rmw_fastrtps#842; likelier on a loaded machine). The
    request is therefore sent again, up to ``attempts`` times within the same total ``timeout_s``.
    Only for requests whose repetition changes nothing (e.g. setting parameters to given values)."""
    for _ in range(attempts):
        future = client.call_async(request)
        executor.spin_until_future_complete(future, timeout_sec=timeout_s / attempts)
        if future.done():
            return future.result()
        client.remove_pending_request(future)
    return None
