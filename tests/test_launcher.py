"""`artrack launch` and tracking.launch.py: one graph file, one expansion, real child processes."""

from __future__ import annotations

import os
import py_compile
import stat
import sys
from pathlib import Path

import pytest
from conftest import REPO

from artrack.config import read_yaml
from artrack.errors import InputError
from artrack.launcher import Launcher, NodeSpec, expand_graph, parse_overrides

GRAPH = REPO / "config" / "graph.yaml"


def test_graph_expands_one_blob_node_per_camera_with_substituted_parameters():
    specs = expand_graph(read_yaml(GRAPH), "graph.yaml", parse_overrides(["cameras=[a, b]", "estimator=baseline"]))
    names = [s.name for s in specs]
    assert names == ["blob_features_a", "blob_features_b", "skeleton", "feedback_projection", "body_publisher",
                     "bag_recorder", "bag_player"]
    blob_a = specs[0]
    assert blob_a.parameters["camera_name"] == "a"
    assert blob_a.parameters["lockstep"] is True  # whole-value substitution keeps the YAML type
    skeleton = specs[2]
    assert skeleton.parameters["camera_names"] == ["a", "b"]
    assert skeleton.parameters["estimator"] == "baseline"
    assert [s.until_exit for s in specs].count(True) == 1


def test_disabled_node_is_not_started_and_unknown_variable_is_refused():
    specs = expand_graph(read_yaml(GRAPH), "graph.yaml", {"record": False})
    assert "bag_recorder" not in [s.name for s in specs]
    with pytest.raises(InputError, match="graph.yaml: no graph variable 'camras'"):
        expand_graph(read_yaml(GRAPH), "graph.yaml", {"camras": ["a"]})
    with pytest.raises(InputError, match="expected key=value"):
        parse_overrides(["estimator"])


def test_player_waits_for_every_node_the_graph_starts():
    """``${graph_nodes}``: the bag player's wait_for_nodes names every node started, whichever are
    enabled (a loose_limbed node that started late once missed the first frames of a lockstep replay
    and changed its result), and the built-in name cannot be redefined."""
    graph = read_yaml(GRAPH)
    specs = expand_graph(graph, "graph.yaml", {"cameras": ["a", "b"], "loose_limbed": True, "record": False})
    player = next(s for s in specs if s.name == "bag_player")
    assert player.parameters["wait_for_nodes"] == [s.name for s in specs]
    assert "loose_limbed" in player.parameters["wait_for_nodes"]
    assert "bag_recorder" not in player.parameters["wait_for_nodes"]
    graph["variables"]["graph_nodes"] = []
    with pytest.raises(InputError, match="'graph_nodes' is built in"):
        expand_graph(graph, "graph.yaml")


def test_ros2_launch_file_compiles_and_reads_the_same_graph():
    launch_file = REPO / "src" / "artrack_nodes" / "launch" / "tracking.launch.py"
    py_compile.compile(str(launch_file), doraise=True)  # launch_ros itself is not installable here
    text = launch_file.read_text()
    assert "expand_graph" in text and "graph.yaml" in text


def _fake_prefix(tmp_path: Path, scripts: dict[str, str]) -> Path:
    """An AMENT prefix whose lib/artrack_nodes holds small real executables."""
    lib = tmp_path / "prefix" / "lib" / "artrack_nodes"
    lib.mkdir(parents=True)
    for name, body in scripts.items():
        exe = lib / name
        exe.write_text(f"#!{sys.executable}\n{body}\n")
        exe.chmod(exe.stat().st_mode | stat.S_IEXEC)
    return tmp_path / "prefix"


def test_launcher_restarts_a_crashing_node_and_ends_with_the_until_exit_node(tmp_path, monkeypatch):
    count = tmp_path / "starts.txt"
    prefix = _fake_prefix(tmp_path, {
        "crasher": f"open({str(count)!r}, 'a').write('x'); raise SystemExit(3)",
        "sleeper": "import time; time.sleep(60)",
        "player": "import time; time.sleep(5); raise SystemExit(0)",
    })
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix) + os.pathsep + os.environ.get("AMENT_PREFIX_PATH", ""))
    specs = [NodeSpec("crasher", "crasher", restarts=2), NodeSpec("sleeper", "sleeper"),
             NodeSpec("player", "player", until_exit=True)]
    launcher = Launcher(specs, log_dir=tmp_path / "logs")
    assert launcher.run(timeout_s=30) == 0
    assert count.read_text() == "xxx", "started once and restarted twice"
    assert launcher.procs["sleeper"].poll() is not None, "the others are shut down when the player ends"
    assert (tmp_path / "logs" / "player.log").is_file()
    assert not launcher.tmp.exists(), "the parameter files' temporary directory is removed"
    assert not launcher.logs, "the log files are closed"
