"""Options of the opt-in hardware tests (``pytest -m hardware``): the devices' URLs."""


def pytest_addoption(parser):
    group = parser.getgroup("glassmap hardware")
    group.addoption("--laser-url", default=None,
                    help="URL of a real Hokuyo for -m hardware (or GLASSMAP_LASER_URL), e.g. tcp://192.168.0.10:10940")
    group.addoption("--base-url", default=None,
                    help="URL of a real Pioneer for -m hardware (or GLASSMAP_BASE_URL), e.g. serial:///dev/ttyUSB0")
