"""The README's Python example runs exactly as printed, from an empty directory, and trains."""
from __future__ import annotations

import re
import subprocess
import sys

from conftest import ROOT


def test_the_readme_example_runs_as_printed_and_both_flows_learn(tmp_path):
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    assert len(blocks) == 1
    assert len(blocks[0].strip().splitlines()) <= 25
    (tmp_path / "example.py").write_text(blocks[0])
    done = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = re.findall(r"mode (\w): test loss ([\d.]+) -> ([\d.]+)", done.stdout)
    assert [mode for mode, _, _ in lines] == ["R", "C"], done.stdout
    for mode, first, last in lines:
        assert float(last) < 0.5 * float(first), (mode, first, last)  # each flow at least halves the loss
