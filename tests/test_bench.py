"""The benchmark harness's own helpers (the benchmarks themselves live in benchmarks/)."""

import os
import platform

import pytest

from rangesurf.bench import machine_description


@pytest.mark.skipif(not os.path.exists("/proc/cpuinfo"), reason="reads the processor model from Linux's /proc/cpuinfo")
def test_the_machine_description_names_the_processor_model_and_the_cores():
    with open("/proc/cpuinfo") as stream:
        models = [line.split(":", 1)[1].strip() for line in stream if line.startswith("model name")]
    description = machine_description()
    if models:
        assert f"({models[0]})" in description
    assert description.startswith(platform.machine())
    assert f"{os.cpu_count()} cores" in description
