"""Every command a user runs answers ``--help`` (the brief: "--help on every command").

The installed node executables (where `ros2 run` looks for them), `artrack` and each of its
sub-commands, the bench scripts and the shell scripts: exit 0 and a usage text, without doing
their work (nothing is written to the repository, no node joins the graph). A shell script given
an argument it does not know says so in one line and exits 2.
"""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest
from conftest import NODE_BIN, REPO

SUBCOMMANDS = ["synth", "track", "bag-from-videos", "eval", "overlay", "launch"]
SCRIPTS = ["setup.sh", "fetch_pose2sim.sh", "two_hosts.sh"]  # (env.sh is sourced, not run)


def commands() -> dict[str, list[str]]:
    """name -> argv of every user-facing command, ``--help`` appended."""
    out = {exe.name: [str(exe), "--help"] for exe in sorted(NODE_BIN.iterdir()) if exe.is_file()}
    out.update({f"artrack {sub}": [str(NODE_BIN / "artrack"), sub, "--help"] for sub in SUBCOMMANDS})
    out.update({f"bench/{p.name}": [sys.executable, str(p), "--help"] for p in sorted((REPO / "bench").glob("*.py"))})
    out.update({f"scripts/{s}": ["bash", str(REPO / "scripts" / s), "--help"] for s in SCRIPTS})
    return out


def _status() -> str:
    return subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], cwd=REPO, capture_output=True,
                          text=True).stdout


def test_every_command_answers_help(env):
    cmds = commands()
    assert {"skeleton", "blob_features", "feedback_projection", "camera_ingest", "artrack", "bench/real_video.py",
            "scripts/setup.sh"} <= set(cmds)
    before = _status()

    def run(argv):
        return subprocess.run(argv, env=env, cwd=REPO, capture_output=True, text=True, timeout=120)

    with ThreadPoolExecutor(4) as pool:
        results = dict(zip(cmds, pool.map(run, cmds.values()), strict=True))
    failed = {name: (p.returncode, (p.stdout + p.stderr)[-300:]) for name, p in results.items()
              if p.returncode != 0 or "usage" not in p.stdout.lower()}
    assert not failed, failed
    assert _status() == before, "a --help wrote into the repository"


@pytest.mark.parametrize("script", ["setup.sh", "fetch_pose2sim.sh"])  # (two_hosts.sh takes a bag and a directory)
def test_shell_scripts_refuse_an_unknown_argument(script, env):
    proc = subprocess.run(["bash", str(REPO / "scripts" / script), "--no-such-option"], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0, proc.stderr
    assert "unknown argument '--no-such-option'" in proc.stderr
