"""The wheel users install (the Docker image installs one) carries every module and every Hydra
config file: a package or config group folder missing from pyproject's package list would ship
a server that cannot import itself or compose its defaults."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).parents[1]


def _source_copy(dest: Path) -> Path:
    """What the Dockerfile copies, so the build's scratch files stay out of the checkout."""
    dest.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(ROOT / name, dest / name)
    for package in ("fedhpg", "common", "envs", "server", "agent", "conf"):
        shutil.copytree(
            ROOT / package, dest / package, ignore=shutil.ignore_patterns("__pycache__")
        )
    return dest


def test_wheel_ships_every_config_file(tmp_path: Path) -> None:
    source = _source_copy(tmp_path / "src")
    build = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp_path),
            str(source),
        ],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert build.returncode == 0, build.stderr
    assert "absent from the `packages` configuration" not in build.stderr, build.stderr
    (wheel,) = tmp_path.glob("fedhpg-*.whl")
    shipped = {
        name.removeprefix("fedhpg/conf/")
        for name in zipfile.ZipFile(wheel).namelist()
        if name.startswith("fedhpg/conf/") and name.endswith(".yaml")
    }
    expected = {p.relative_to(ROOT / "conf").as_posix() for p in (ROOT / "conf").rglob("*.yaml")}
    assert expected and shipped == expected
    modules = {
        name.removeprefix("fedhpg/")
        for name in zipfile.ZipFile(wheel).namelist()
        if name.startswith("fedhpg/") and name.endswith(".py")
    }
    folders = {"common": "common", "envs": "envs", "server": "server", "agent": "agent"}
    sources = {
        f"{folder}/{p.relative_to(ROOT / folder).as_posix()}"
        for folder in folders
        for p in (ROOT / folder).rglob("*.py")
        if "__pycache__" not in p.parts
    }
    assert sources and sources <= modules, sorted(sources - modules)
