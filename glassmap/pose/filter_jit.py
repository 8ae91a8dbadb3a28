"""Compiled small-matrix steps of the pose filter and estimator (:mod:`glassmap.pose.filter`,
:mod:`glassmap.pose.estimator`), numba ``njit``: one call instead of a dozen numpy calls on 3x3 arrays.

Bit for bit the numpy code they replace: numpy multiplies float64 matrices with BLAS (dgemm), whose
x86-64 OpenBLAS kernels on FMA machines accumulate each element as a chain of fused multiply-adds over
k = 0, 1, ... starting from zero; ``_matmul`` does the same (``_fma``: LLVM's ``fma`` intrinsic, one
rounding), and every other operation is the numpy code's, in its order (no fast-math). Cosines and sines
are libm's, as numpy's float64 ones. Poses (x, y, yaw) in m, m, rad; covariances (3, 3) float64.
Compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import numpy as np

from glassmap.jit import LazyKernel


def _fma(a: float, b: float, c: float) -> float:
    """a * b + c with one rounding: replaced by LLVM's intrinsic before the kernels compile."""
    raise RuntimeError("glassmap.pose.filter_jit._fma runs only compiled")


def _fma_intrinsic():
    from numba import types
    from numba.extending import intrinsic

    @intrinsic
    def fma(typingctx, a, b, c):
        sig = types.float64(types.float64, types.float64, types.float64)

        def codegen(context, builder, signature, args):
            return builder.fma(*args)  # llvm.fma.f64

        return sig, codegen

    return fma


class _FmaKernel(LazyKernel):
    """A lazy kernel whose module's ``_fma`` becomes the compiled intrinsic before anything compiles."""

    def compiled(self):
        g = self.py_func.__globals__
        if g["_fma"] is _fma:
            g["_fma"] = _fma_intrinsic()
        return super().compiled()


def _jit(py_func):
    return _FmaKernel(py_func, dict(cache=True, nogil=True, error_model="numpy"))


@_jit
def _matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b as numpy's BLAS computes it (each element a fused multiply-add chain over k from 0)."""
    n, m, kk = a.shape[0], b.shape[1], a.shape[1]
    out = np.empty((n, m), np.float64)
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for k in range(kk):
                acc = _fma(a[i, k], b[k, j], acc)
            out[i, j] = acc
    return out


@_jit
def sandwich(j: np.ndarray, c: np.ndarray) -> np.ndarray:
    """j @ c @ j.T (square matrices)."""
    return _matmul(_matmul(j, c), j.T)


@_jit
def _wrap(a: float) -> float:
    """glassmap.types.wrap_angle of one angle (rad)."""
    return np.pi - (np.pi - a) % (2 * np.pi)


@_jit
def _jacobian_a(c: float, s: float, b: np.ndarray) -> np.ndarray:
    """d compose(a, b) / d a, with c, s = cos, sin of a's yaw (motion.compose_jacobians)."""
    out = np.zeros((3, 3), np.float64)
    out[0, 0] = 1.0
    out[1, 1] = 1.0
    out[2, 2] = 1.0
    out[0, 2] = -s * b[0] - c * b[1]
    out[1, 2] = c * b[0] - s * b[1]
    return out


@_jit
def carried(a: np.ndarray, b: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """ja @ cov @ ja.T with ja = compose_jacobians(a, b)[0]: a covariance of pose a carried to a (+) b."""
    return sandwich(_jacobian_a(np.cos(a[2]), np.sin(a[2]), b), cov)


@_jit
def rotated(a: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """jb @ cov @ jb.T with jb = compose_jacobians(a, .)[1]: a covariance in the frame of pose a, in a's
    parent frame."""
    c, s = np.cos(a[2]), np.sin(a[2])
    jb = np.zeros((3, 3), np.float64)
    jb[0, 0], jb[0, 1], jb[1, 0], jb[1, 1], jb[2, 2] = c, -s, s, c, 1.0
    return sandwich(jb, cov)


@_jit
def predict(pose: np.ndarray, delta: np.ndarray, q: np.ndarray, cov: np.ndarray, actual: np.ndarray,
            cross: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """PoseEKF.predict: (pose (+) delta, ja cov ja^T + jb q jb^T symmetrized, the same of ``actual``,
    ja @ cross)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    ja = _jacobian_a(c, s, delta)
    new_pose = np.empty(3, np.float64)
    new_pose[0] = pose[0] + c * delta[0] - s * delta[1]
    new_pose[1] = pose[1] + s * delta[0] + c * delta[1]
    new_pose[2] = _wrap(pose[2] + delta[2])
    jq = rotated(pose, q)
    p = sandwich(ja, cov) + jq
    p = 0.5 * (p + p.T)
    a = sandwich(ja, actual) + jq
    a = 0.5 * (a + a.T)
    return new_pose, p, a, _matmul(ja, cross)


@_jit
def compose_covariance(a: np.ndarray, b: np.ndarray, cov_a: np.ndarray, cov_b: np.ndarray) -> np.ndarray:
    """motion.compose_covariance: ja cov_a ja^T + jb cov_b jb^T symmetrized, with (ja, jb) =
    compose_jacobians(a, b)."""
    out = carried(a, b, cov_a) + rotated(a, cov_b)
    return 0.5 * (out + out.T)


@_jit
def motion_covariance(dx: float, dy: float, d: float, var_along: float, var_lat: float, var_yaw: float
                      ) -> np.ndarray:
    """MotionNoise.covariance's 3x3 from its variances for a motion (dx, dy) of length d (m): the xy block
    rot @ diag(var_along, var_lat) @ rot.T with rot = [[c, -s], [s, c]], (c, s) = (dx, dy) / d, where
    d > 1e-9 (else diag(var_along, var_lat)), and var_yaw."""
    cov = np.zeros((3, 3), np.float64)
    if d > 1e-9:
        rot = np.empty((2, 2), np.float64)
        c, s = dx / d, dy / d
        rot[0, 0], rot[0, 1], rot[1, 0], rot[1, 1] = c, -s, s, c
        diag = np.zeros((2, 2), np.float64)
        diag[0, 0], diag[1, 1] = var_along, var_lat
        cov[:2, :2] = sandwich(rot, diag)
    else:
        cov[0, 0], cov[1, 1] = var_along, var_lat
    cov[2, 2] = var_yaw
    return cov


def warm_up() -> None:
    """Load (or, the first time on a machine, compile) these kernels now, with the argument types the
    filter and the estimator pass, rather than at the first scan."""
    z3, e = np.zeros(3), np.eye(3)
    predict(z3, z3, e, e, e, e)
    carried(z3, z3, e)
    rotated(z3, e)
    compose_covariance(z3, z3, e, e)
    motion_covariance(1.0, 0.0, 1.0, 0.0, 0.0, 0.0)
