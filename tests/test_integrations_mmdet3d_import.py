"""Importing drcpo's MMDetection3D adapter: a clear error without mmdet3d (any environment)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

_WITHOUT_MMDET3D = """
import sys
sys.modules["mmdet3d"] = None  # as if not installed, whatever this environment holds
try:
    import drcpo.integrations.mmdet3d
except ImportError as exc:
    print(exc)
else:
    print("imported")
"""


def test_import_without_mmdet3d_says_what_is_missing():
    run = subprocess.run(
        [sys.executable, "-c", _WITHOUT_MMDET3D], capture_output=True, text=True, check=True
    )
    assert "drcpo.integrations.mmdet3d needs MMDetection3D 1.x" in run.stdout
    # the message sends the user to a page that exists
    assert "see docs/mmdet3d.md" in run.stdout
    assert (Path(__file__).parents[1] / "docs" / "mmdet3d.md").is_file()


def test_import_drcpo_does_not_import_the_adapter():
    code = "import sys, drcpo; print('drcpo.integrations.mmdet3d' in sys.modules)"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "False"
