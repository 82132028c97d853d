"""Stage the extension for Blender's builder: manifest, package contents and wheels.

    python tools/stage.py --openexr 3.5.3 --package multiscale_camera \
        --manifest blender_manifest.toml --cache .cache/wheels build/stage

The OpenEXR wheels are downloaded once per (platform, Python) into the cache with
``pip download``; a combination PyPI does not have is reported and skipped. The staged
manifest is the committed one plus ``platforms`` and ``wheels`` naming what was found.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

# Blender platform -> pip platform tags, best first.
PLATFORM_TAGS = {
    # Blender 4.2+ for Linux needs glibc 2.28; older manylinux wheels run there too.
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    # Blender 4.2+ for macOS needs macOS 11.2; pip also accepts older macOS tags.
    "macos-arm64": ["macosx_11_0_arm64"],
    "macos-x64": ["macosx_11_0_x86_64"],
}
# Blender 4.2 to 5.0 bundle Python 3.11, Blender 5.1+ 3.13; Linux distributions 3.13, 3.14.
PYTHONS = ["3.11", "3.13", "3.14"]


def cached_wheel(cache: Path, version: str, platform: str, python: str) -> Path | None:
    """Return the OpenEXR wheel for one combination, downloading it when absent.

    Returns None when PyPI has no such wheel. Raises CalledProcessError on other pip
    failures (no network, for instance), so an incomplete cache never passes silently.
    """
    folder = cache / f"openexr-{version}" / f"{platform}-py{python}"
    wheels = sorted(folder.glob("*.whl"))
    if wheels:
        return wheels[0]
    folder.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--quiet",
        "--no-deps",
        "--only-binary=:all:",
        "--python-version",
        python,
        "--dest",
        str(folder),
    ]
    for tag in PLATFORM_TAGS[platform]:
        cmd += ["--platform", tag]
    cmd.append(f"OpenEXR=={version}")
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        if "No matching distribution found" in proc.stderr:
            return None
        sys.stderr.write(proc.stdout + proc.stderr)
        proc.check_returncode()
    wheels = sorted(folder.glob("*.whl"))
    return wheels[0] if wheels else None


def staged_manifest(text: str, platforms: list[str], wheels: list[str]) -> str:
    """The manifest with ``platforms`` and ``wheels`` inserted before its first table."""
    data = tomllib.loads(text)
    for key in ("platforms", "wheels"):
        if key in data:
            raise SystemExit(f"blender_manifest.toml sets {key!r}; leave it to tools/stage.py")

    def toml_list(items: list[str]) -> str:
        return "[\n" + "".join(f'    "{item}",\n' for item in items) + "]\n"

    generated = f"platforms = {toml_list(platforms)}wheels = {toml_list(wheels)}\n"
    lines = text.splitlines(keepends=True)
    first_table = next(
        (i for i, line in enumerate(lines) if line.lstrip().startswith("[")), len(lines)
    )
    if first_table == len(lines) and lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    return "".join(lines[:first_table] + [generated] + lines[first_table:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("stage", type=Path, help="folder to (re)create")
    parser.add_argument("--openexr", required=True, help="OpenEXR version to bundle")
    parser.add_argument("--package", type=Path, default=Path("multiscale_camera"))
    parser.add_argument("--manifest", type=Path, default=Path("blender_manifest.toml"))
    parser.add_argument("--cache", type=Path, default=Path(".cache/wheels"))
    args = parser.parse_args()

    if not (args.package / "__init__.py").is_file():
        raise SystemExit(f"{args.package}/__init__.py is missing: nothing to package")

    shutil.rmtree(args.stage, ignore_errors=True)
    shutil.copytree(args.package, args.stage, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    (args.stage / "wheels").mkdir()

    platforms, wheels, missing = [], [], []
    for platform in PLATFORM_TAGS:
        found = False
        for python in PYTHONS:
            wheel = cached_wheel(args.cache, args.openexr, platform, python)
            if wheel is None:
                missing.append(f"{platform} / Python {python}")
                continue
            found = True
            entry = f"./wheels/{wheel.name}"
            if entry not in wheels:  # a universal2 wheel serves both macOS platforms
                shutil.copy2(wheel, args.stage / "wheels" / wheel.name)
                wheels.append(entry)
        if found:
            platforms.append(platform)

    manifest = staged_manifest(args.manifest.read_text(), platforms, wheels)
    (args.stage / "blender_manifest.toml").write_text(manifest)

    print(
        f"staged {args.stage}: {len(wheels)} OpenEXR {args.openexr} wheels for "
        f"{', '.join(platforms)}"
    )
    for combo in missing:
        print(f"  not on PyPI, skipped: OpenEXR {args.openexr} for {combo}")


if __name__ == "__main__":
    main()
