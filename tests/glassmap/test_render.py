"""Paper colours: free white, unknown green, occupied blue -> gray -> red; row 0 = highest y."""

import numpy as np

from glassmap.render import BLUE, GRAY, GREEN, RED, confidence_colours, glass_confidence_png, glass_confidence_rgb


def test_colour_scale_end_points():
    c = confidence_colours(np.array([0.0, 0.5, 1.0, 0.25]))
    assert np.allclose(c[0], BLUE) and np.allclose(c[1], GRAY) and np.allclose(c[2], RED)
    assert np.allclose(c[3], (BLUE + GRAY) / 2)


def test_image_layout(tmp_path):
    conf = np.full((2, 3), np.nan, dtype=np.float32)
    conf[0, 0] = 1.0  # bottom-left cell is certainly glass
    free = np.zeros((2, 3), dtype=bool)
    free[1, 2] = True  # top-right free
    img = glass_confidence_rgb(conf, free)
    assert img.shape == (2, 3, 3) and img.dtype == np.uint8
    assert img[1, 0].tolist() == [255, 0, 0]  # flipped: row 0 of the image is the top
    assert img[0, 2].tolist() == [255, 255, 255]
    assert np.allclose(img[0, 0], np.round(GREEN * 255), atol=1)
    path = glass_confidence_png(str(tmp_path / "m.png"), conf, free, scale=3, crop=False)
    import matplotlib.image as mpimg

    assert mpimg.imread(path).shape[:2] == (6, 9)
