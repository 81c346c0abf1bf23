"""``--version`` on every entry point and ``fedhpg.__version__``: the installed package's
version, printed before anything is composed or started (exit 0, nothing written)."""

from __future__ import annotations

import importlib.metadata
import subprocess
from pathlib import Path

import pytest
from procs import BIN

import fedhpg

SCRIPTS = [
    "fedhpg-run",
    "fedhpg-server",
    "fedhpg-agent",
    "fedhpg-plot",
    "fedhpg-keys",
    "fedhpg-cluster",
    "fedhpg-plan",
    "fedhpg-record",
]


def test_the_package_has_a_version() -> None:
    assert fedhpg.__version__ == importlib.metadata.version("fedhpg")


@pytest.mark.parametrize("script", SCRIPTS)
def test_every_entry_point_says_its_version(script: str, tmp_path: Path) -> None:
    result = subprocess.run(
        [str(BIN / script), "--version"], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"{script} {fedhpg.__version__}\n"
    assert not list(tmp_path.iterdir()), "nothing written"
