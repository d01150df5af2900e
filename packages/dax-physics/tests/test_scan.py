"""checkpointed_scan: the same carry and outputs as lax.scan for every segment length
(including the skipped surplus steps of the segment rule), the same gradients, and clear
errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dax_physics import checkpointed_scan
from dax_physics.scan import segment_layout


def _body(c, x):
    c = jnp.sin(c) * 1.1 + x * c[::-1]
    return c, jnp.sum(c * c)


C0 = jnp.linspace(0.1, 0.9, 4)
XS = jnp.linspace(-1.0, 1.0, 23 * 4).reshape(23, 4)


@pytest.mark.parametrize("short_last", [False, True])
@pytest.mark.parametrize("segment", [None, 1, 5, 7, 23, 40])
def test_equals_a_plain_scan_for_every_segment_length(segment, short_last):
    want_c, want_y = jax.lax.scan(_body, C0, XS)
    got_c, got_y = jax.jit(lambda c, xs: checkpointed_scan(
        _body, c, xs, segment=segment, short_last=short_last))(C0, XS)
    what = f"segment={segment}, short_last={short_last}"
    np.testing.assert_array_equal(got_c, want_c, err_msg=f"carry, {what}")
    assert got_y.shape == want_y.shape == (23,), f"ys shape {got_y.shape}"
    np.testing.assert_array_equal(got_y, want_y, err_msg=f"ys, {what}")


def test_gradients_equal_with_and_without_checkpointing():
    def loss(c0, segment):
        c, ys = checkpointed_scan(_body, c0, XS, segment=segment)
        return jnp.sum(c) + jnp.sum(ys)

    def loss_short(c0, segment):
        c, ys = checkpointed_scan(_body, c0, XS, segment=segment, short_last=True)
        return jnp.sum(c) + jnp.sum(ys)

    plain = jax.grad(lambda c: loss(c, None))(C0)
    for segment in (5, 7):  # 5 x 5 (2 skipped), 4 x 6 (1 skipped); short: 4 x 5 + 3, 3 x 6 + 5
        for f in (loss, loss_short):
            seg = jax.grad(lambda c, s=segment, f=f: f(c, s))(C0)
            np.testing.assert_allclose(seg, plain, rtol=1e-6,
                                       err_msg=f"gradient with segment={segment}, {f.__name__}")
    c, ys = checkpointed_scan(lambda c, _: (c + 1, None), jnp.zeros(()), length=10, segment=3,
                              short_last=True)
    assert float(c) == 10.0 and ys is None, f"short_last without xs: carry {c}, ys {ys}"


def test_length_without_xs_and_bad_arguments():
    c, ys = checkpointed_scan(lambda c, _: (c + 1, None), jnp.zeros(()), length=10, segment=3)
    assert float(c) == 10.0 and ys is None, f"got carry {c}, ys {ys}"
    with pytest.raises(ValueError, match="needs xs or length"):
        checkpointed_scan(_body, C0)
    with pytest.raises(ValueError, match="segment must be a positive int"):
        checkpointed_scan(_body, C0, XS, segment=0)
    with pytest.raises(ValueError, match="does not match"):
        checkpointed_scan(_body, C0, XS, length=5)


def test_segments_are_equal_and_at_most_the_segment_length():
    assert segment_layout(200, 20) == (10, 20)
    assert segment_layout(36, 10) == (4, 9)    # not 3 x 10 + 6: one body to compile
    assert segment_layout(50, 20) == (3, 17)   # one surplus step, skipped
    assert segment_layout(16, None) == (1, 16) and segment_layout(16, 40) == (1, 16)
    for n in range(1, 60):
        for seg in range(1, 25):
            k, length = segment_layout(n, seg)
            assert length <= seg and 0 <= k * length - n < k, (n, seg, k, length)
