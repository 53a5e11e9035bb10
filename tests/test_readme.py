"""The README's Python API example runs as written (the code block is taken from README.md, not copied here)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def readme_example() -> str:
    """The first ```python block after the README's "### Python API" heading."""
    text = (REPO / "README.md").read_text()
    section = text.split("### Python API", 1)[1]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "README.md: no ```python block under ### Python API"
    return match.group(1)


@pytest.mark.skipif(not (REPO / "dfvo/checkpoints/flow.safetensors").is_file(), reason="no shipped checkpoints")
def test_readme_python_example_runs_as_written(tmp_path: Path) -> None:
    code = readme_example()
    assert len([ln for ln in code.splitlines() if ln.strip()]) <= 10  # the front door's promise: ten lines
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 4 and lines[0].startswith("init")
    assert all(line.split()[0] in ("E", "PnP", "constant_motion") for line in lines[1:]), proc.stdout
    assert not list(tmp_path.iterdir())  # the API writes no files
