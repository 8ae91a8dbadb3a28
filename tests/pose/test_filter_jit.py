"""The compiled small-matrix steps of the pose filter give the numpy code they replaced bit for bit (where
numpy's BLAS multiplies with fused multiply-adds, as OpenBLAS does on FMA machines), and within rounding
everywhere."""

import numpy as np

from glassmap.pose.filter_jit import carried, compose_covariance, motion_covariance, predict, rotated, sandwich
from glassmap.pose.motion import compose_jacobians
from glassmap.types import wrap_angle


def _numpy_matmul_uses_fma() -> bool:
    # element (0, 0) is -(1 + 2^-26) + x^2 with x = 1 + 2^-27: 2^-54 with a fused multiply-add, 0 without
    x = 1.0 + 2.0 ** -27
    a = np.array([[-1.0, x, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    b = np.array([[1.0 + 2.0 ** -26, 0.0, 0.0], [x, 0.0, 0.0], [0.0, 0.0, 0.0]])
    return (a @ b)[0, 0] == 2.0 ** -54


FMA = _numpy_matmul_uses_fma()


def _same(x, y):
    if not FMA:  # the kernels' fused products differ from numpy's in the last bits only
        y = np.asarray(y)
        return np.allclose(x, y, rtol=1e-12, atol=1e-12 * float(np.abs(y).max()))
    return np.asarray(x).tobytes() == np.asarray(y).tobytes()  # bit for bit, signed zeros included


def test_the_kernels_products_are_within_rounding_of_numpys_anywhere():
    rng = np.random.default_rng(13)
    for _ in range(2000):
        a, c = rng.normal(size=(3, 3)), _cov(rng)
        scale = np.abs(a) @ np.abs(c) @ np.abs(a).T
        assert np.all(np.abs(sandwich(a, c) - a @ c @ a.T) <= 1e-14 * scale)


def _np_jacobians(a, b):
    c, s = np.cos(a[2]), np.sin(a[2])
    return (np.array([[1.0, 0.0, -s * b[0] - c * b[1]], [0.0, 1.0, c * b[0] - s * b[1]], [0.0, 0.0, 1.0]]),
            np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))


def _cov(rng):
    a = rng.normal(size=(3, 3))
    cov = a @ a.T * 10 ** rng.uniform(-10, 1)
    if rng.random() < 0.2:
        cov[2], cov[:, 2] = 0.0, -0.0
    return cov


def _pose(rng, scale=20.0):
    p = rng.normal(0, scale, 3) * rng.choice([1.0, 1e-7, 0.0], 3)
    p[2] = p[2] % 7.0 - 3.5
    return p


def test_sandwich_carried_and_rotated_equal_numpy_matmul():
    rng = np.random.default_rng(10)
    for _ in range(5000):
        a, b, cov = _pose(rng), _pose(rng, 0.1), _cov(rng)
        ja, jb = _np_jacobians(a, b)
        assert _same(sandwich(ja, cov), ja @ cov @ ja.T)
        assert _same(carried(a, b, cov), ja @ cov @ ja.T)
        assert _same(rotated(a, cov), jb @ cov @ jb.T)


def test_predict_equals_the_numpy_filter_step():
    rng = np.random.default_rng(11)
    for _ in range(5000):
        pose, delta, q, cov, act, cross = _pose(rng), _pose(rng, 0.05), _cov(rng), _cov(rng), _cov(rng), _cov(rng)
        ja, jb = _np_jacobians(pose, delta)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        ref_pose = np.array([pose[0] + c * delta[0] - s * delta[1], pose[1] + s * delta[0] + c * delta[1],
                             float(wrap_angle(pose[2] + delta[2]))])
        p = ja @ cov @ ja.T + jb @ q @ jb.T
        a = ja @ act @ ja.T + jb @ q @ jb.T
        out = predict(pose, delta, q, cov, act, cross)
        for x, y in zip(out, (ref_pose, 0.5 * (p + p.T), 0.5 * (a + a.T), ja @ cross)):
            assert _same(x, y)


def test_motion_covariance_equals_the_numpy_rotation():
    rng = np.random.default_rng(12)
    for i in range(5000):
        d = rng.normal(size=2) * 10 ** rng.uniform(-6, 0) * (i % 10 > 0)  # every tenth a motion of zero length
        n = float(np.hypot(d[0], d[1]))
        va, vl, vy = rng.uniform(0, 1e-3, 3)
        ref = np.zeros((3, 3))  # MotionNoise.covariance's numpy code
        if n > 1e-9:
            c, s = float(d[0]) / n, float(d[1]) / n
            rot = np.array([[c, -s], [s, c]])
            ref[:2, :2] = rot @ np.diag([va, vl]) @ rot.T
        else:
            ref[:2, :2] = np.diag([va, vl])
        ref[2, 2] = vy
        assert _same(motion_covariance(float(d[0]), float(d[1]), n, va, vl, vy), ref)


def test_compose_covariance_equals_the_numpy_jacobians():
    rng = np.random.default_rng(14)
    for _ in range(5000):
        a, b, cov_a, cov_b = _pose(rng), _pose(rng, 0.5), _cov(rng), _cov(rng)
        ja, jb = compose_jacobians(a, b)  # motion.compose_covariance's numpy code
        out = ja @ cov_a @ ja.T + jb @ cov_b @ jb.T
        assert _same(compose_covariance(a, b, cov_a, cov_b), 0.5 * (out + out.T))
