"""The layering of docs/ARCHITECTURE.md: the core (``artrack``) imports without ROS.

Every module of the core is imported in a fresh interpreter in which rclpy, the rosidl runtime
and every ROS message package (``*_msgs``, ``builtin_interfaces``) refuse to import, as on a
machine with numpy / scipy / OpenCV / rosbags / mcap but no ROS 2. The nodes
(``artrack_nodes``) are the only layer that may use rclpy.
"""

from __future__ import annotations

import pkgutil
import subprocess
import sys

from conftest import REPO

CORE = REPO / "src" / "artrack_nodes" / "artrack"

# A meta-path finder that refuses the ROS client library and message packages, then imports each
# module named on the command line and prints the ROS modules that got imported anyway.
_PROBE = r"""
import importlib, sys

ROS = ("rclpy", "rosidl_runtime_py", "rosidl_parser", "rpyutils", "builtin_interfaces")

def is_ros(name):
    top = name.partition(".")[0]
    return top in ROS or top.endswith("_msgs")

class NoRos:
    def find_spec(self, name, path=None, target=None):
        if is_ros(name):
            raise ImportError(f"{name} is not available (the core must not need ROS)")
        return None

sys.meta_path.insert(0, NoRos())
for module in sys.argv[1:]:
    importlib.import_module(module)
print(" ".join(sorted(m for m in sys.modules if is_ros(m))))
"""


def core_modules() -> list[str]:
    return sorted(f"artrack.{m.name}" for m in pkgutil.iter_modules([str(CORE)]) if m.name != "__main__")


def probe(*modules: str) -> subprocess.CompletedProcess:
    """Import ``modules`` in a fresh interpreter without ROS (``_PROBE``), the core on its path."""
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(CORE.parent), "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run([sys.executable, "-c", _PROBE, *modules], capture_output=True, text=True, timeout=120,
                          cwd=REPO, env=env)


def test_every_core_module_imports_without_ros():
    modules = core_modules()
    assert {"artrack.blobs", "artrack.skeleton", "artrack.pipeline", "artrack.messages", "artrack.bags"} <= set(modules)
    proc = probe(*modules)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip() == "", f"ROS modules imported by the core: {proc.stdout}"


def test_the_probe_refuses_rclpy():
    """The check itself can fail: a module that imports rclpy is caught."""
    proc = probe("artrack_nodes.common")
    assert proc.returncode != 0 and "the core must not need ROS" in proc.stderr, proc.stderr[-2000:]


def test_core_modules_are_listed_in_the_architecture():
    """Every core module has its row in docs/ARCHITECTURE.md's module table."""
    text = (REPO / "docs" / "ARCHITECTURE.md").read_text()
    missing = [m for m in core_modules() if f"`{m.split('.', 1)[1]}.py`" not in text]
    assert not missing, f"not in docs/ARCHITECTURE.md: {missing}"
