"""Test configuration: picks the Warp device (CPU by default, ``--device cuda:0`` on the GPU machine)."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("WARP_QUIET", "1")


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device", action="store", default="cpu", help="Warp device to run tests on (cpu, cuda:0)")


@pytest.fixture(scope="session")
def device(request: pytest.FixtureRequest) -> str:
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)  # no per-module load lines
    wp.init()
    name = request.config.getoption("--device")
    if name != "cpu" and not wp.is_cuda_available():
        pytest.skip(f"device {name} requested but CUDA is not available")
    return name
