"""Every command a user runs answers ``--help`` (the brief: "--help on every command").

The installed node executables (where `ros2 run` looks for them), `artrack` and each of its
sub-commands, the bench scripts and the shell scripts: exit 0 and a usage text, without doing
their work (nothing written where they run, no tracked file changed, no node joining a graph). A
shell script given an argument it does not know says so in one line and exits 2.
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


def _tracked_changes() -> str:
    """The repository's changed tracked files (untracked ones left out: another xdist worker's test may
    be writing its own)."""
    return subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True,
                          text=True).stdout


def test_every_command_answers_help(env, tmp_path):
    cmds = commands()
    assert {"skeleton", "blob_features", "feedback_projection", "camera_ingest", "artrack", "bench/real_video.py",
            "scripts/setup.sh"} <= set(cmds)
    before = _tracked_changes()

    def run(argv):  # run from an empty directory, which must stay empty
        return subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)

    with ThreadPoolExecutor(4) as pool:
        results = dict(zip(cmds, pool.map(run, cmds.values()), strict=True))
    failed = {name: (p.returncode, (p.stdout + p.stderr)[-300:]) for name, p in results.items()
              if p.returncode != 0 or "usage" not in p.stdout.lower()}
    assert not failed, failed
    assert not any(tmp_path.iterdir()), f"a --help wrote {sorted(p.name for p in tmp_path.iterdir())}"
    assert _tracked_changes() == before, "a --help changed a file of the repository"


@pytest.mark.parametrize("script", ["setup.sh", "fetch_pose2sim.sh"])  # (two_hosts.sh takes a bag and a directory)
def test_shell_scripts_refuse_an_unknown_argument(script, env):
    proc = subprocess.run(["bash", str(REPO / "scripts" / script), "--no-such-option"], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0, proc.stderr
    assert "unknown argument '--no-such-option'" in proc.stderr
