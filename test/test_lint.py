"""The linter runs with the tests (ament_flake8 settings: line length 99)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_flake8_clean():
    dirs = [d for d in ("ooi_seg_ros", "test", "benchmarks") if (ROOT / d).is_dir()]
    res = subprocess.run([sys.executable, "-m", "flake8", *dirs], cwd=ROOT,
                         capture_output=True, text=True)
    assert res.returncode == 0, "flake8 found problems:\n" + res.stdout + res.stderr
