"""Node parameters: declared ranges contain the defaults, config/nodes.yaml documents what the nodes
declare, and an out-of-range value stops a node at start-up with one line (real executable)."""

from __future__ import annotations

import importlib
import subprocess

import pytest
import yaml
from conftest import NODE_BIN, REPO

NODES = ["blob_features", "edge_features", "skeleton", "feedback_projection", "body_publisher", "bag_player",
         "bag_recorder", "camera_ingest", "loose_limbed", "particle_tracker", "object_features"]


def _module(name: str):
    return importlib.import_module(f"artrack_nodes.{name}")


@pytest.mark.parametrize("name", NODES)
def test_nodes_yaml_documents_the_declared_parameters(name):
    text = (REPO / "config" / "nodes.yaml").read_text()
    documented = yaml.safe_load(text)[name]["ros__parameters"]
    m = _module(name)
    declared = {p[0]: p[1] for p in m.PARAMS}
    for key, value in documented.items():
        assert key in declared, f"config/nodes.yaml: {name}.{key} is not a parameter of the node"
        assert value == declared[key], f"config/nodes.yaml: {name}.{key} default {value!r} != {declared[key]!r}"
    limits, runtime = getattr(m, "LIMITS", {}) or {}, set(getattr(m, "RUNTIME", ()) or ())
    lines = text.split(f"\n{name}:\n", 1)[1].split("\n\n", 1)[0].splitlines()

    def comments(key: str) -> str:
        """The comment block just above ``key``."""
        i = lines.index(next(ln for ln in lines if ln.startswith(f"    {key}:")))
        block = []
        while i > 0 and lines[i - 1].startswith("    #"):
            i -= 1
            block.append(lines[i])
        return "\n".join(block)

    for key, (lo, hi) in limits.items():
        assert lo <= declared[key] <= hi, f"{name}.{key}: default outside its range"
        assert f"range [{lo}, {hi}]" in comments(key), f"config/nodes.yaml: range of {name}.{key} not documented"
    for key in runtime:
        assert "runtime" in comments(key), f"config/nodes.yaml does not mark {name}.{key} as runtime"


@pytest.mark.graph
def _assert_stops_with_one_line(env, node: str, args: list[str], names: str) -> None:
    """The node, started with ``args``, exits 1 with one stderr line naming the parameter ``names``."""
    proc = subprocess.run([str(NODE_BIN / node), "--ros-args", *args], env=env, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 1
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"{node}: ") and names in lines[0], proc.stderr


def test_out_of_range_parameter_stops_the_node_with_one_line(env):
    _assert_stops_with_one_line(env, "skeleton", ["-p", "sync_timeout_s:=-1.0"], "sync_timeout_s")


@pytest.mark.graph
def test_refinement_outside_a_lockstep_graph_stops_the_node_with_one_line(env):
    """Free-running (lockstep false by default) feature nodes have moved past the frame a refinement
    asks for; with edges it is allowed since stop 63 (edge_features answer refinements)."""
    _assert_stops_with_one_line(env, "skeleton", ["-p", "refine_passes:=2"], "refine_passes")


@pytest.mark.graph
def test_feedback_switched_off_at_run_time_over_dds(env, probe, tmp_path):
    """A parameter client (rcl_interfaces services, as `ros2 param set`) turns blob_features'
    feedback off while it runs; out-of-range and start-up-only values are refused."""
    from conftest import call_service, spin_until
    from rcl_interfaces.srv import GetParameters, SetParameters
    from rclpy.parameter import Parameter

    node, executor = probe
    log = tmp_path / "blob.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([str(NODE_BIN / "blob_features"), "--ros-args", "-r", "__node:=blob_features_camq",
                                 "-p", "camera_name:=camq"], env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        setter = node.create_client(SetParameters, "/blob_features_camq/set_parameters")
        getter = node.create_client(GetParameters, "/blob_features_camq/get_parameters")
        assert spin_until(executor, lambda: setter.service_is_ready() and getter.service_is_ready(), 30), \
            log.read_text()

        def call(client, request):
            response = call_service(executor, client, request, timeout_s=20)
            assert response is not None, "parameter service did not answer"
            return response

        results = call(setter, SetParameters.Request(parameters=[
            Parameter(name, value=value).to_parameter_msg() for name, value in
            [("feedback", False), ("fps", 0.5), ("camera_name", "camz")]])).results
        assert [r.successful for r in results] == [True, False, False], [r.reason for r in results]
        values = call(getter, GetParameters.Request(names=["feedback", "fps", "camera_name"])).values
        assert (values[0].bool_value, values[1].double_value, values[2].string_value) == (False, 30.0, "camq")
        assert spin_until(executor, lambda: "parameter feedback set to False" in log.read_text(), 10)
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=10)
