"""The likelihood field's compiled coarse maximum equals the scipy filter it replaced, bit for bit."""

import numpy as np
import pytest
from scipy import ndimage

from glassmap.pose.field_jit import forward_maximum


@pytest.mark.parametrize("shape, f", [((60, 45), 4), ((7, 5), 4), ((3, 2), 5), ((1, 1), 4), ((20, 30), 1),
                                      ((20, 30), 2), ((40, 33), 3)])
def test_forward_maximum_equals_scipy_maximum_filter(shape, f):
    rng = np.random.default_rng(f * 1000 + shape[0])
    a = rng.normal(size=shape).astype(np.float32)
    a[rng.random(shape) < 0.6] = np.float32(np.log(0.01))  # the floor, many ties
    want = ndimage.maximum_filter(a, size=f, origin=-(f // 2), mode="nearest")
    assert forward_maximum(a, f).tobytes() == want.tobytes()
