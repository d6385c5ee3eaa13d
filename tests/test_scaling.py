"""The scaling study: its exponent fit, case sizes, baseline checkout and --quick results."""

import json
import subprocess

import numpy as np
import pytest

from benchmarks.__main__ import main
from benchmarks.scaling import REFERENCE_PIXELS, REFERENCE_SIZE, checkout, colour_size, fitted_exponent


def test_fitted_exponent_recovers_a_power_law():
    rows = [{"object_pixels": p, "frames": n, "seconds": 0.5 * (p * n) ** 1.1}
            for p in (1e5, 3e5, 1e6) for n in (5, 20)]
    assert fitted_exponent(rows) == pytest.approx(1.1, abs=1e-9)
    assert fitted_exponent(rows[:1] + [{"timeout": 60.0}]) is None  # one finished case fits nothing


def test_colour_size_scales_the_two_megapixel_frame_to_the_pixel_target():
    assert colour_size(REFERENCE_PIXELS) == (1696, 1152)  # 1708 x 1136 rounded to multiples of 8 x SF 4
    W, H = REFERENCE_SIZE
    for target in (100_000, 2_000_000):
        w, h = colour_size(target)
        assert w % 32 == 0 and h % 32 == 0
        assert w * h / (W * H) == pytest.approx(target / REFERENCE_PIXELS, rel=0.1)


def test_baseline_checkout_is_a_temporary_worktree_of_the_revision():
    with checkout("HEAD") as tree:
        assert (tree / "benchmarks" / "speed.py").is_file()
        head = subprocess.run(["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True).stdout
        assert head == subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout
    assert not tree.exists()


def test_quick_scaling_writes_rows_table_and_plot(tmp_path):
    assert main(["scaling", "--quick", "--out", str(tmp_path)]) == 0
    rows = json.loads((tmp_path / "scaling.json").read_text())
    assert [r["frames"] for r in rows] == [3, 5]
    for r in rows:
        assert r["object_pixels"] > 10_000 and r["seconds"] > 0 and r["peak_mb"] > 100
        assert r["sweeps"] >= 1 and all(isinstance(c, int) for c in r["finest_cg_iterations"])
    table = (tmp_path / "scaling.md").read_text()
    assert "fitted exponent" in table and (tmp_path / "scaling.png").stat().st_size > 1000
    assert np.isfinite(fitted_exponent(rows))
