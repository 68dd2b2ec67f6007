"""`runtime.fixed_shapes`: batches padded to a fixed size."""

import numpy as np

from ffcgs_jax.runtime.fixed_shapes import pad_rows


def test_short_batches_repeat_their_first_row_and_full_ones_pass_through():
    x = np.arange(6.0).reshape(3, 2)
    np.testing.assert_array_equal(pad_rows(x, 5), [[0, 1], [2, 3], [4, 5], [0, 1], [0, 1]])
    assert pad_rows(x, 3) is x and pad_rows(x, 2) is x
    assert pad_rows([1, 2], 3).tolist() == [1, 2, 1]
    assert pad_rows(np.zeros((0, 4)), 8).shape == (0, 4)  # nothing to repeat: callers never pad an empty batch
