"""`artrack launch` and tracking.launch.py: one graph file, one expansion, real child processes."""

from __future__ import annotations

import json
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


def test_launcher_reports_each_nodes_cpu_time_summed_over_restarts(tmp_path, monkeypatch, capfd):
    """Per-node CPU (user + system, /proc) while the graph ran: a node that burns 0.3 s of CPU, exits and
    is restarted to burn 0.3 s again counts both; a node that sleeps counts little."""
    marks = tmp_path / "burns.txt"
    burn = ("import time, sys\n"
            "t0 = time.process_time()\n"
            "while time.process_time() - t0 < 0.3: pass\n"
            f"open({str(marks)!r}, 'a').write('x')\n"
            f"if open({str(marks)!r}).read() == 'x': raise SystemExit(3)\n"
            "time.sleep(60)")
    player = (f"import os, time\nwhile not (os.path.exists({str(marks)!r}) and open({str(marks)!r}).read() == 'xx'):\n"
              "    time.sleep(0.05)\n"
              "time.sleep(0.3)\n")
    prefix = _fake_prefix(tmp_path, {"burner": burn, "sleeper": "import time; time.sleep(60)", "player": player})
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix) + os.pathsep + os.environ.get("AMENT_PREFIX_PATH", ""))
    specs = [NodeSpec("burner", "burner", restarts=1), NodeSpec("sleeper", "sleeper"),
             NodeSpec("player", "player", until_exit=True)]
    launcher = Launcher(specs, log_dir=tmp_path / "logs")
    assert launcher.run(timeout_s=60) == 0
    cpu = json.loads((tmp_path / "logs" / "cpu.json").read_text())["cpu_s"]
    assert set(cpu) == {"burner", "sleeper", "player"}
    assert cpu["burner"] >= 0.6, cpu
    assert cpu["sleeper"] < 0.3 and cpu["sleeper"] < cpu["burner"] - 0.4, cpu
    assert list(cpu)[0] == "burner", "largest first"
    assert "artrack launch: CPU s by node: burner " in capfd.readouterr().err
