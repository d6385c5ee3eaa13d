"""Open3D's plotly viewer is put off (o3d_mvps.lazy_imports): ``import open3d`` after ``import
o3d_mvps`` loads neither plotly nor Dash, and Open3D's plotly functions still work."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(code: str) -> str:
    """Run ``code`` in a fresh interpreter (this worktree's package first); its stdout."""
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_open3d_import_skips_plotly_and_dash_and_its_viewer_still_works():
    out = _run(
        "import sys, numpy as np, o3d_mvps, open3d as o3d\n"
        "print('dash' in sys.modules, 'plotly' in sys.modules)\n"
        "cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.eye(3)))\n"
        "fig = o3d.visualization.get_plotly_fig([cloud])\n"
        "print(type(fig).__name__, len(fig.data), 'dash' in sys.modules)\n"
        "real = sys.modules['open3d.visualization.draw_plotly']\n"
        "print(o3d.visualization.draw_plotly is real.draw_plotly, hasattr(real, '__o3d_mvps_stand_in__'))\n")
    assert out.split("\n")[:3] == ["False False", "Figure 1 True", "True False"], out


def test_nothing_changes_when_open3d_came_first():
    out = _run("import sys, open3d, o3d_mvps\n"
               "from o3d_mvps.lazy_imports import defer_open3d_plotly\n"
               "print('dash' in sys.modules, defer_open3d_plotly())\n")
    assert out.strip() == "True False", out
