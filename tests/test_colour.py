"""The sRGB transfer functions and the integer-code decode table (o3d_mvps.colour)."""

import numpy as np
import pytest

from o3d_mvps.colour import (CodedColours, codes_to_linear, decode_table, float_frame, is_coded, linear_to_srgb,
                             srgb_to_linear)


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


# --- coded frames (CodedColours) -------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_coded_frames_decode_to_the_float_frames(dtype):
    """A frame of every code decodes (indexing, :func:`float_frame` of :meth:`frame`,
    :func:`codes_to_linear`: OpenCV's LUT for 8 bits) to the very float32 frame that gathering
    :func:`decode_table` gives: what a capture held before frames were kept coded."""
    rng = np.random.default_rng(1)
    top = np.iinfo(dtype).max
    codes = [rng.integers(0, top + 1, size=(9, 7, 3)).astype(dtype) for _ in range(2)]
    codes[0][0, 0] = [0, top, top // 2]
    for srgb in (True, False):
        coded = CodedColours.from_codes(codes, srgb=srgb)
        assert coded.shape == (2, 9, 7, 3) and len(coded) == 2 and coded.tables.shape == (2, 3, top + 1)
        for i in range(2):
            expected = decode_table(8 * np.dtype(dtype).itemsize, srgb)[codes[i]]  # NumPy's gather
            np.testing.assert_array_equal(codes_to_linear(codes[i], srgb=srgb), expected)
            assert coded[i].dtype == np.float32
            np.testing.assert_array_equal(coded[i], expected)
            np.testing.assert_array_equal(float_frame(coded.frame(i)), expected)
            assert coded.frame(i)[0] is coded.codes[i]  # shared, not copied
        assert coded.nbytes == 2 * 9 * 7 * 3 * np.dtype(dtype).itemsize + coded.tables.nbytes


def test_divided_frames_equal_the_float_frames_divided():
    """A white balance folded into the tables gives each pixel the float32 that dividing the
    decoded frame by the balance (as float32) gives, bit for bit; the codes are shared."""
    rng = np.random.default_rng(2)
    codes = [rng.integers(0, 256, size=(6, 5, 3)).astype(np.uint8) for _ in range(3)]
    balance = rng.uniform(0.9, 1.1, size=(3, 3))
    coded = CodedColours.from_codes(codes)
    divided = coded.divided(balance)
    for i in range(3):
        expected = (coded[i] / balance[i].astype(np.float32)).astype(np.float32)
        np.testing.assert_array_equal(divided[i], expected)
        assert divided.codes[i] is coded.codes[i]
    assert not np.array_equal(divided[1], coded[1])


def test_coded_frames_refuse_mixed_or_float_codes_and_wrong_tables():
    codes8 = np.zeros((4, 4, 3), np.uint8)
    with pytest.raises(ValueError, match="must all be uint8 or all uint16"):
        CodedColours([codes8, codes8.astype(np.uint16)], np.zeros((2, 3, 256), np.float32))
    with pytest.raises(ValueError, match="must all be uint8 or all uint16"):
        CodedColours([codes8.astype(np.float32)], np.zeros((1, 3, 256), np.float32))
    with pytest.raises(ValueError, match=r"tables must be \(n, 3, K\) = \(1, 3, 256\)"):
        CodedColours([codes8], np.zeros((1, 3, 65536), np.float32))
    assert not is_coded(codes8) and is_coded((codes8, np.zeros((3, 256), np.float32)))
