"""Options and fixtures of the opt-in hardware tests (``pytest -m hardware``): the devices' URLs."""

import os

import pytest


def pytest_addoption(parser):
    group = parser.getgroup("glassmap hardware")
    group.addoption("--laser-url", default=None,
                    help="URL of a real Hokuyo for -m hardware (or GLASSMAP_LASER_URL), e.g. tcp://192.168.0.10:10940")
    group.addoption("--base-url", default=None,
                    help="URL of a real Pioneer for -m hardware (or GLASSMAP_BASE_URL), e.g. serial:///dev/ttyUSB0")


def _device_url(request, option: str, env: str, what: str) -> str:
    url = request.config.getoption(option, default=None) or os.environ.get(env)
    if not url:
        pytest.skip(reason=f"no {what}: pass {option} or set {env}")
    return url


@pytest.fixture
def laser_url(request) -> str:
    """URL of a real laser (--laser-url or GLASSMAP_LASER_URL); the test is skipped without one."""
    return _device_url(request, "--laser-url", "GLASSMAP_LASER_URL", "laser")


@pytest.fixture
def base_url(request) -> str:
    """URL of a real Pioneer (--base-url or GLASSMAP_BASE_URL); the test is skipped without one."""
    return _device_url(request, "--base-url", "GLASSMAP_BASE_URL", "robot")
