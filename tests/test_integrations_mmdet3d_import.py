"""Importing drcpo's MMDetection3D adapter: a clear error without mmdet3d (any environment)."""

from __future__ import annotations

import subprocess
import sys

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
    assert "Training with MMDetection3D" in run.stdout


def test_import_drcpo_does_not_import_the_adapter():
    code = "import sys, drcpo; print('drcpo.integrations.mmdet3d' in sys.modules)"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip() == "False"
