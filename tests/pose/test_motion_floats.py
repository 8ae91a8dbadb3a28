"""The SE(2) helpers on Python floats give the numpy expressions they replaced bit for bit."""

import numpy as np

from glassmap.pose.motion import OdometryBuffer, _wrap, compose, compose_jacobians, relative
from glassmap.types import Odometry, wrap_angle


def _np_compose(a, b):
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], float(wrap_angle(a[2] + b[2]))])


def _np_relative(a, b):
    c, s = np.cos(a[2]), np.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, float(wrap_angle(b[2] - a[2]))])


def _np_jacobians(a, b):
    c, s = np.cos(a[2]), np.sin(a[2])
    return (np.array([[1.0, 0.0, -s * b[0] - c * b[1]], [0.0, 1.0, c * b[0] - s * b[1]], [0.0, 0.0, 1.0]]),
            np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))


def _same(x, y):
    return np.asarray(x).tobytes() == np.asarray(y).tobytes()  # bit for bit, signed zeros included


def test_wrap_equals_wrap_angle_bit_for_bit():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.uniform(-20, 20, 20000), rng.normal(0, 1e-9, 2000),
                        [0.0, -0.0, np.pi, -np.pi, 2 * np.pi, -2 * np.pi, 3 * np.pi, np.nextafter(np.pi, 4),
                         np.nextafter(-np.pi, -4), 1e300, -1e-300]])
    assert _same(wrap_angle(x), [_wrap(float(v)) for v in x])


def test_compose_relative_and_jacobians_equal_the_numpy_code():
    rng = np.random.default_rng(4)
    for _ in range(3000):
        a = rng.normal(0, 20, 3) * rng.choice([1.0, 1e-6, 0.0], 3)
        b = rng.normal(0, 2, 3) * rng.choice([1.0, 1e-6, 0.0], 3)
        a[2], b[2] = a[2] % 7 - 3.5, b[2] % 7 - 3.5
        assert _same(compose(a, b), _np_compose(a, b))
        assert _same(relative(a, b), _np_relative(a, b))
        for x, y in zip(compose_jacobians(a, b), _np_jacobians(a, b)):
            assert _same(x, y)


def test_interpolated_pose_equals_the_numpy_code():
    rng = np.random.default_rng(5)
    buf = OdometryBuffer(horizon=100.0)
    t = np.cumsum(rng.uniform(0.01, 0.05, 200))
    yaw = np.cumsum(rng.normal(0, 0.3, 200))
    for k in range(200):
        buf.add(Odometry(stamp=float(t[k]), x=float(np.cos(k / 9.0) * 3), y=float(k * 0.01),
                         yaw=float(wrap_angle(yaw[k])), v=0.3, omega=0.1))
    for q in rng.uniform(t[0], t[-1], 2000):
        i = int(np.searchsorted(t, q, side="right"))
        p0, p1 = buf._pose[i - 1], buf._pose[i]
        a = (q - buf._t[i - 1]) / (buf._t[i] - buf._t[i - 1])
        y = p0[2] + a * float(wrap_angle(p1[2] - p0[2]))
        ref = np.array([p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]), float(wrap_angle(y))])
        assert _same(buf.pose_at(float(q)), ref)
