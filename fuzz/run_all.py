"""Fuzz every reader for a fixed number of inputs and record the result in ``benchmarks/results/fuzz.md``.

Run: ``.venv/bin/python fuzz/run_all.py [RUNS]`` (default 100,000 per reader; needs atheris).
Each reader runs in its own process (``fuzz/fuzz_readers.py FORMAT -runs=RUNS``); a crash stops that
reader's run and its input is kept in ``fuzz/crashes/`` (turn it into a regression test).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "src"))

from rangesurf.bench import machine_description, write_results  # noqa: E402


def main() -> None:
    runs = int(sys.argv[1]) if len(sys.argv) > 1 else 100_000
    crashes = HERE / "crashes"
    crashes.mkdir(exist_ok=True)
    lines = [f"Machine: {machine_description()}. Command: `.venv/bin/python fuzz/run_all.py {runs}`.", "",
             "libFuzzer (atheris) on each reader, seeded with a small frame written by rangesurf's writer and, "
             "for .3d and .ply, the first 64 kB of the real scans; peak RSS from libFuzzer's own report.", "",
             "| reader | inputs | seconds | inputs/s | crashes | peak RSS (MB) |", "|---|---:|---:|---:|---:|---:|"]
    for form in ("3d", "ply", "pcd", "npz", "npy", "png"):
        start = time.perf_counter()
        process = subprocess.run(
            [sys.executable, str(HERE / "fuzz_readers.py"), form, f"-runs={runs}", f"-artifact_prefix={crashes}/{form}-",
             "-rss_limit_mb=4096"],
            capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
        seconds = time.perf_counter() - start
        log = process.stdout + process.stderr
        done = re.findall(r"Done (\d+) runs", log)
        executed = int(done[-1]) if done else int((re.findall(r"#(\d+)\s", log) or ["0"])[-1])
        rss = (re.findall(r"rss: (\d+)Mb", log) or ["?"])[-1]
        crashed = int(process.returncode != 0)
        lines.append(f"| {form} | {executed} | {seconds:.0f} | {executed / max(seconds, 1e-9):.0f} | {crashed} | {rss} |")
        print(lines[-1], flush=True)
        if crashed:
            (crashes / f"{form}.log").write_text(log[-5000:])
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.2f}."]
    write_results(HERE.parent / "benchmarks" / "results", "fuzz.md", lines)


if __name__ == "__main__":
    main()
