"""`artrack launch`: start a node graph as separate OS processes.

The graph file (config/graph.yaml) lists the nodes, their executables and
parameters; nodes marked ``per_camera`` are started once per camera. Each
node gets a generated ROS parameter file. The launcher forwards SIGINT and
SIGTERM, restarts a node that crashes (at most ``restarts`` times), ends the
graph when a node marked ``until_exit`` (the bag player) exits, and shuts the
others down cleanly (SIGINT, then SIGTERM, then SIGKILL). At the end it says how
much CPU each node used while the graph ran (user + system time from
/proc/<pid>/stat, summed over a node's restarts, its teardown not counted): one
line on stderr and, with a log directory, ``cpu.json`` there.

ROS-free: it runs the executables that `ros2 run artrack_nodes <name>` runs
(install/artrack_nodes/lib/artrack_nodes/<name>), found through
AMENT_PREFIX_PATH, so it works where `ros2 launch` is not installed. The same
graph for real ROS installs is src/artrack_nodes/launch/tracking.launch.py.
"""

from __future__ import annotations

import fnmatch
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from .config import read_yaml
from .errors import InputError

PACKAGE = "artrack_nodes"


def find_executable(name: str) -> Path:
    """lib/artrack_nodes/<name> under an AMENT_PREFIX_PATH entry."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidate = Path(prefix) / "lib" / PACKAGE / name
            if candidate.is_file():
                return candidate
    raise InputError(f"executable '{name}' not found in lib/{PACKAGE} of AMENT_PREFIX_PATH (run `make setup`)")


@dataclass
class NodeSpec:
    """One node process of a graph: its name, executable, ROS parameters, how many times it is
    restarted when it dies, and whether the graph ends when it exits (``until_exit``)."""

    name: str
    executable: str
    parameters: dict[str, Any] = field(default_factory=dict)
    restarts: int = 0
    until_exit: bool = False


#: built-in graph variable: the names of every node the graph starts (e.g. the bag player's wait_for_nodes)
GRAPH_NODES = "graph_nodes"


def expand_graph(graph: dict[str, Any], where: str, overrides: dict[str, Any] | None = None) -> list[NodeSpec]:
    """Node specs from a graph mapping; ``${name}`` strings are replaced from ``variables``/overrides,
    and ``${graph_nodes}`` by the names of all the nodes the graph starts."""
    variables = dict(graph.get("variables", {}) or {})
    if GRAPH_NODES in variables:
        raise InputError(f"{where}: variable '{GRAPH_NODES}' is built in (the names of the graph's nodes)")
    unknown = sorted(set(overrides or {}) - set(variables))
    if unknown:
        raise InputError(f"{where}: no graph variable '{unknown[0]}' (variables: {', '.join(variables)})")
    variables.update(overrides or {})
    cameras = list(variables.get("cameras", []))

    def subst(value: Any, camera: str | None) -> Any:
        if isinstance(value, str):
            if value.startswith("${") and value.endswith("}") and value[2:-1] in variables:
                return variables[value[2:-1]]  # whole-value substitution keeps lists/bools
            for key, val in variables.items():
                value = value.replace("${" + key + "}", str(val))
            return value.replace("{camera}", camera or "")
        if isinstance(value, list):
            return [subst(v, camera) for v in value]
        if isinstance(value, dict):
            return {k: subst(v, camera) for k, v in value.items()}
        return value

    started: list[tuple[str, dict, str | None]] = []  # (node name, graph entry, camera)
    for i, entry in enumerate(graph.get("nodes", []) or []):
        if not isinstance(entry, dict) or "executable" not in entry:
            raise InputError(f"{where}: nodes[{i}] has no field 'executable'")
        if subst(entry.get("enabled", True), None) in (False, "false"):
            continue
        per_camera = bool(entry.get("per_camera", False))
        for camera in cameras if per_camera else [None]:
            started.append((subst(entry.get("name", entry["executable"]), camera), entry, camera))
    variables[GRAPH_NODES] = [name for name, _, _ in started]
    return [NodeSpec(name=name, executable=entry["executable"],
                     parameters=subst(dict(entry.get("parameters", {}) or {}), camera),
                     restarts=int(entry.get("restarts", 0)), until_exit=bool(entry.get("until_exit", False)))
            for name, entry, camera in started]


class Launcher:
    """Runs NodeSpecs as child processes until an ``until_exit`` node ends or a signal arrives."""

    def __init__(self, specs: list[NodeSpec], log_dir: Path | None = None, quiet: bool = False):
        self.specs = specs
        self.tmp = Path(tempfile.mkdtemp(prefix="artrack_launch_"))
        self.log_dir = log_dir
        self.quiet = quiet
        self.procs: dict[str, subprocess.Popen] = {}
        self.restarts_left = {s.name: s.restarts for s in specs}
        self.stopping = False
        self.exit_codes: dict[str, int] = {}
        self.logs: list = []
        self.cpu_s: dict[str, dict[int, float]] = {}  # node -> {pid: CPU s at the last look}

    def _start(self, spec: NodeSpec) -> None:
        params = self.tmp / f"{spec.name}.yaml"
        params.write_text(yaml.safe_dump({spec.name: {"ros__parameters": spec.parameters}}))
        cmd = [str(find_executable(spec.executable)), "--ros-args", "-r", f"__node:={spec.name}",
               "--params-file", str(params)]
        out = None
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            out = open(self.log_dir / f"{spec.name}.log", "ab")  # noqa: SIM115 - closed in shutdown()
            self.logs.append(out)
        elif self.quiet:
            out = subprocess.DEVNULL
        self.procs[spec.name] = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT if out else None)

    def _signal(self, signum, _frame) -> None:
        self.stopping = True

    def run(self, timeout_s: float | None = None) -> int:
        """Start everything, supervise, shut down. Returns the until_exit node's exit code (or 0)."""
        old = {s: signal.signal(s, self._signal) for s in (signal.SIGINT, signal.SIGTERM)}
        t0 = time.monotonic()
        result = 0
        try:
            for spec in self.specs:
                self._start(spec)
            while not self.stopping:
                time.sleep(0.1)
                if timeout_s is not None and time.monotonic() - t0 > timeout_s:
                    print(f"artrack launch: timeout after {timeout_s:.0f}s", file=sys.stderr)
                    result = 124
                    break
                done = self._supervise()
                if done is not None:
                    result = done
                    break
        finally:
            self.shutdown()
            for s, handler in old.items():
                signal.signal(s, handler)
        return result

    def _look_at_cpu(self, name: str, proc: subprocess.Popen) -> None:
        """Note a child's CPU time so far (an exited child not yet reaped still shows its final time)."""
        t = process_cpu_s(proc.pid)
        if t is not None:
            self.cpu_s.setdefault(name, {})[proc.pid] = t

    def cpu_by_node(self) -> dict[str, float]:
        """CPU seconds (user + system) each node used, summed over its restarts, largest first."""
        total = {name: sum(by_pid.values()) for name, by_pid in self.cpu_s.items()}
        return dict(sorted(total.items(), key=lambda kv: -kv[1]))

    def _supervise(self) -> int | None:
        for spec in self.specs:
            proc = self.procs.get(spec.name)
            if proc is None:
                continue
            self._look_at_cpu(spec.name, proc)
            if proc.poll() is None:
                continue
            code = proc.returncode
            self.exit_codes[spec.name] = code
            if spec.until_exit:
                return code
            if self.restarts_left[spec.name] > 0:
                self.restarts_left[spec.name] -= 1
                print(f"artrack launch: {spec.name} exited ({code}); restarting", file=sys.stderr)
                self._start(spec)
            else:
                del self.procs[spec.name]
                print(f"artrack launch: {spec.name} exited ({code})", file=sys.stderr)
        return None

    def shutdown(self, grace_s: float = 5.0) -> None:
        """Stop every child (SIGINT, then SIGTERM, then SIGKILL), then close the log files and
        remove the parameter files' temporary directory."""
        for name, proc in self.procs.items():
            self._look_at_cpu(name, proc)  # (before the teardown)
        self._report_cpu()
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            alive = [p for p in self.procs.values() if p.poll() is None]
            if not alive:
                break
            for p in alive:
                p.send_signal(sig)
            deadline = time.monotonic() + grace_s
            while time.monotonic() < deadline and any(p.poll() is None for p in alive):
                time.sleep(0.05)
        for log in self.logs:
            log.close()
        self.logs.clear()
        shutil.rmtree(self.tmp, ignore_errors=True)


    def _report_cpu(self) -> None:
        cpu = self.cpu_by_node()
        if not cpu:
            return
        print("artrack launch: CPU s by node: " + ", ".join(f"{n} {t:.2f}" for n, t in cpu.items())
              + f"; total {sum(cpu.values()):.2f}", file=sys.stderr)
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            (self.log_dir / "cpu.json").write_text(json.dumps({"cpu_s": cpu}) + "\n")


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of process ``pid`` (Linux /proc; None where there is none)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2:].split()  # (the command name may hold spaces)
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def launch(graph_path: str, overrides: dict[str, Any] | None = None, timeout_s: float | None = None,
           log_dir: str | None = None, only: list[str] | None = None) -> int:
    """Run a graph file. ``only``: fnmatch patterns of node names to start (one host's share of a
    graph spread over several machines); without an until_exit node among them the graph runs
    until SIGINT/SIGTERM or the timeout."""
    graph = read_yaml(graph_path)
    specs = expand_graph(graph, Path(graph_path).name, overrides)
    if only:
        specs = [s for s in specs if any(fnmatch.fnmatch(s.name, pat) for pat in only)]
    if not specs:
        raise InputError(f"{graph_path}: no nodes to start" + (f" matching {only}" if only else ""))
    return Launcher(specs, Path(log_dir) if log_dir else None).run(timeout_s)


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """`key=value` strings; values parsed as YAML (so true, 3, [a, b] work)."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise InputError(f"--set '{item}': expected key=value")
        key, value = item.split("=", 1)
        out[key] = yaml.safe_load(value) if value else ""
    return out
