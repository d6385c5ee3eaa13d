"""The sRGB transfer functions and the integer-code decode table (o3d_mvps.colour)."""

import numpy as np
import pytest

from o3d_mvps.colour import codes_to_linear, decode_table, linear_to_srgb, srgb_to_linear


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("srgb", [True, False])
def test_table_decode_equals_the_formula(dtype, srgb):
    """Every code decodes to the very float32 the formula gives on code / max (float64): the
    table changes no pixel of a read capture."""
    top = np.iinfo(dtype).max
    codes = np.arange(top + 1, dtype=dtype).reshape(-1, 1)
    value = codes / float(top)
    expected = srgb_to_linear(value) if srgb else value.astype(np.float32)
    decoded = codes_to_linear(codes, srgb=srgb)
    assert decoded.dtype == np.float32 and decoded.shape == codes.shape
    np.testing.assert_array_equal(decoded, expected)


def test_table_is_shared_and_read_only():
    assert decode_table(8) is decode_table(8)
    with pytest.raises(ValueError, match="read-only"):
        decode_table(8)[0] = 1.0


def test_codes_must_be_integers():
    with pytest.raises(ValueError, match="expected uint8 or uint16 codes, got float32"):
        codes_to_linear(np.zeros((2, 2, 3), np.float32))


def test_round_trip_within_one_8bit_step():
    codes = np.arange(256, dtype=np.uint8)
    back = np.rint(linear_to_srgb(codes_to_linear(codes)).astype(np.float64) * 255)
    np.testing.assert_array_equal(back, codes)
