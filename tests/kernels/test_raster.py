"""`kernels.triangles.rasterise`: which pixel centres a screen-space triangle covers, and the z-test."""

import numpy as np

from ffcgs_jax.kernels import triangles


def _cover(sx, sy, w, h, **kw):
    out = np.full(w * h, -1)
    triangles.rasterise(np.asarray(sx, float), np.asarray(sy, float), w, h,
                        lambda t, r, c: (t, None), out, np.maximum, **kw)
    return out.reshape(h, w)


def test_a_triangle_covers_the_centres_inside_it_whichever_way_it_winds():
    rng = np.random.default_rng(0)
    sx, sy = rng.uniform(-2, 18, (20, 3)), rng.uniform(-2, 14, (20, 3))
    v, u = np.mgrid[0:12, 0:16] + 0.5
    for i in range(20):
        a = triangles.signed_area(sx[i : i + 1], sy[i : i + 1])[0]
        e = [(sx[i, (k + 1) % 3] - sx[i, k]) * (v - sy[i, k]) - (sy[i, (k + 1) % 3] - sy[i, k]) * (u - sx[i, k])
             for k in range(3)]
        inside = np.all([np.sign(a) * x > 1e-6 for x in e], 0)
        border = np.any([np.abs(x) <= 1e-6 for x in e], 0)
        for order in ([0, 1, 2], [0, 2, 1]):
            got = _cover(sx[i : i + 1, order], sy[i : i + 1, order], 16, 12) == 0
            assert not (got ^ inside)[~border].any(), i


def test_the_nearest_fragment_wins_and_a_margin_widens_the_cover():
    sx, sy = np.array([[0.0, 16, 0], [16, 16, 0]]), np.array([[0.0, 0, 12], [0, 12, 12]])
    got = _cover(sx, sy, 16, 12)
    assert (got >= 0).all() and got[0, 0] == 0 and got[11, 15] == 1  # two halves of the image, no gap between
    assert (_cover(sx[[0, 0, 1]], sy[[0, 0, 1]], 16, 12) == np.where(got == 0, 1, 2)).all()  # the max wins
    wide = _cover([[3.3, 8.7, 3.3]], [[3.3, 3.3, 8.7]], 16, 12, centre=0.0, margin=0.5)
    tight = _cover([[3.3, 8.7, 3.3]], [[3.3, 3.3, 8.7]], 16, 12, centre=0.0)
    assert (wide[tight == 0] == 0).all() and (wide == 0).sum() > (tight == 0).sum()
