"""The wheel installs `offworld`, the project's command, beside the package."""

from __future__ import annotations

import subprocess
import sysconfig
from pathlib import Path

import offworld_gym


def test_the_wheel_installs_the_offworld_command():
    installed = Path(sysconfig.get_path("scripts")) / "offworld"
    assert installed.is_file(), f"{installed} (pip's scripts directory)"
    out = subprocess.run([str(installed), "--version"], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"offworld {offworld_gym.__version__}"
    help_text = subprocess.run([str(installed), "twin", "--help"], capture_output=True, text=True, timeout=30)
    assert help_text.returncode == 0, help_text.stderr
    assert "Usage: offworld twin" in help_text.stdout
