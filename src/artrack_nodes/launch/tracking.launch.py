"""The artrack node graph for real ROS 2 installs: `ros2 launch artrack_nodes tracking.launch.py`.

Reads the same graph file as `artrack launch` (config/graph.yaml, installed to
share/artrack_nodes/config) and expands it with the same function
(artrack.launcher.expand_graph), so both launchers start identical nodes with
identical parameters. Graph variables are launch arguments:

    ros2 launch artrack_nodes tracking.launch.py bag:=bags/demo.mcap out:=out/graph \
        cameras:="[cam01, cam02]" estimator:=baseline lockstep:=false

(`launch_ros` is not on PyPI, so this file is exercised only by a syntax and
expansion test here; `artrack launch` is the launcher that runs on this machine.)
"""

from __future__ import annotations

import os

import yaml
from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from artrack.config import read_yaml
from artrack.launcher import expand_graph

PACKAGE = "artrack_nodes"


def _graph_file() -> str:
    return os.path.join(get_package_share_directory(PACKAGE), "config", "graph.yaml")


def _nodes(context, graph_file: LaunchConfiguration):
    path = graph_file.perform(context)
    graph = read_yaml(path)
    overrides = {}
    for key in graph.get("variables", {}) or {}:
        value = LaunchConfiguration(key).perform(context)
        if value != "":
            overrides[key] = yaml.safe_load(value)  # "[cam01, cam02]" -> list, "false" -> bool
    actions = []
    for spec in expand_graph(graph, path, overrides):
        actions.append(
            Node(
                package=PACKAGE,
                executable=spec.executable,
                name=spec.name,
                parameters=[spec.parameters],
                respawn=spec.restarts > 0,
                output="screen",
                # the graph ends when the bag has been played, as with `artrack launch`
                on_exit=Shutdown(reason=f"{spec.name} finished") if spec.until_exit else None,
            )
        )
    return actions


def generate_launch_description() -> LaunchDescription:
    graph_file = LaunchConfiguration("graph")
    args = [DeclareLaunchArgument("graph", default_value=_graph_file(), description="graph file (config/graph.yaml)")]
    for key, value in (read_yaml(_graph_file()).get("variables", {}) or {}).items():
        args.append(DeclareLaunchArgument(key, default_value="", description=f"graph variable (default: {value})"))
    return LaunchDescription([*args, OpaqueFunction(function=_nodes, args=[graph_file])])
