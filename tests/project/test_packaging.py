"""vservo installs exactly one top-level import name, vservo, and nothing else."""

import subprocess
import sys
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_distribution_installs_one_import_name():
    names = {name for name, distributions in metadata.packages_distributions().items() if "vservo" in distributions}
    assert names == {"vservo"}


def test_the_folders_are_not_import_names_of_their_own(tmp_path):
    """Neither from elsewhere nor from the source tree (where the folders are on sys.path)."""
    for where in (tmp_path, ROOT):
        for name in ("core", "app", "robot_models", "static"):
            result = subprocess.run([sys.executable, "-c", f"import {name}"], cwd=where, capture_output=True, text=True)
            assert result.returncode != 0, f"import {name} worked in {where}"
            assert "ModuleNotFoundError" in result.stderr or f"imported as vservo.{name}" in result.stderr
    result = subprocess.run(
        [sys.executable, "-c", "import vservo.core.servo.loop, vservo.app.server"], cwd=tmp_path, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr
