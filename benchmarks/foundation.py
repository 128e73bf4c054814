"""Foundation benchmarks: simulator frames/s per sensor; reader load times vs Open3D and NumPy.

Run: ``.venv/bin/python benchmarks/foundation.py`` (install the ``bench`` extra
for the Open3D columns). Writes ``benchmarks/results/foundation.{json,md}``,
which the README quotes.
"""

from __future__ import annotations

import json
from pathlib import Path

from rangesurf.bench import default_data_root, format_results, run_foundation_benchmarks


def main() -> None:
    results = run_foundation_benchmarks(default_data_root())
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / "foundation.json").write_text(json.dumps(results, indent=2) + "\n")
    table = format_results(results)
    (out / "foundation.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
