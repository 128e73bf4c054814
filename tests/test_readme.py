"""The README's Python example runs and its claims hold."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


def test_readme_python_example_runs(tmp_path, monkeypatch, capsys):
    if not (SHARED_DATA / "uos-3dtk" / "scan001.3d").is_file() or not (SHARED_DATA / "bunny" / "bun045.ply").is_file():
        pytest.skip(f"real scans not found at {SHARED_DATA} (shared test data lives beside the project)")
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    assert blocks, "README has no python example"
    monkeypatch.chdir(tmp_path)  # the example writes files
    for block in blocks:
        exec(compile(block.replace("../shared/data", str(SHARED_DATA)), "README.md", "exec"), {})
    # The valid fraction quoted in a comment is the one printed.
    quoted = re.search(r'print\(f"\{scan.valid.mean\(\):.3f\}"\)\s+# ([0-9.]+)', blocks[0])
    assert quoted and quoted.group(1) in capsys.readouterr().out
