"""Shared fixtures: the `blender` command, the built extension zip, running Blender.

Tests never touch the real Blender user folder: BLENDER_USER_RESOURCES points at a
session temp folder before anything imports bpy (tests that install set their own).
"""

from __future__ import annotations

import atexit
import functools
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

_USER_RESOURCES = tempfile.mkdtemp(prefix="multiscale-blender-user-")
atexit.register(shutil.rmtree, _USER_RESOURCES, ignore_errors=True)
os.environ["BLENDER_USER_RESOURCES"] = _USER_RESOURCES


def blender_command() -> str:
    """$BLENDER, else the repository's tools/blender."""
    return os.environ.get("BLENDER") or str(REPO / "tools" / "blender")


def run_blender(
    args: list[str],
    env: dict[str, str] | None = None,
    timeout: float = 600,
    check: bool = True,
    blender: str | None = None,
) -> subprocess.CompletedProcess:
    """Run `blender *args` (from the repository root) and return the finished process.

    ``env`` is added to the current environment. With ``check`` (the default) a non-zero
    exit fails the test, showing the command, stdout and stderr.
    """
    cmd = [blender or blender_command(), *map(str, args)]
    proc = subprocess.run(
        cmd,
        cwd=REPO,
        env={**os.environ, **(env or {})},
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if check:
        assert proc.returncode == 0, (
            f"{' '.join(cmd)}\nexited with {proc.returncode}\n"
            f"--- stdout ---\n{proc.stdout}\n--- stderr ---\n{proc.stderr}"
        )
    return proc


def blender_modules_after(imports: str) -> tuple[int, str]:
    """Run ``imports`` (Python statements) in a fresh interpreter from the repository
    root; (exit code, output): non-zero when any of bpy, mathutils, bmesh or gpu got
    imported (the output names them)."""
    code = (
        f"import sys; {imports}; "
        "bad = sorted(m for m in sys.modules "
        "if m.split('.')[0] in ('bpy', 'mathutils', 'bmesh', 'gpu')); "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    return out.returncode, out.stdout + out.stderr


@pytest.fixture(scope="session")
def blender() -> str:
    """Path (or name) of the `blender` command the e2e tests run."""
    return blender_command()


@pytest.fixture(name="run_blender", scope="session")
def run_blender_fixture(blender):
    """``run_blender(args, env=None, timeout=600, check=True)`` with $BLENDER."""
    return functools.partial(run_blender, blender=blender)


@pytest.fixture(scope="session")
def linux_zip() -> Path:
    """The built linux-x64 extension zip (named by dist/LINUX_ZIP)."""
    marker = REPO / "dist" / "LINUX_ZIP"
    path = REPO / marker.read_text().strip() if marker.is_file() else None
    if path is None or not path.is_file():
        pytest.fail("no built extension zip (dist/LINUX_ZIP): run `make build` first")
    return path
