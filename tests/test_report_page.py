"""report.html as a person opens it: headless Chromium (Debian's, driven by playwright) loads the
pages that ``refine`` and ``reconstruct`` write, with no console error, no request leaving the
machine, every figure decoded and the 3D view drawn; and the page shows the report.json
contract's sections when they are there.

Chromium comes from the system (``make setup`` installs Debian's ``chromium``); this test does
not skip without it: it fails and says how to install it.
"""

import io
import json
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from o3d_mvps import write_capture
from o3d_mvps.cli import main
from o3d_mvps.report_page import REPORT_HTML, report_page_html
from o3d_mvps.synthetic import render_ring

TINY_SOLVER = ["--levels", "2", "--iterations", "2"]
CHROMIUM = "/usr/bin/chromium"
#: DESIGN.md section 6: WebGL through SwiftShader, headless, as root, on a closed network.
FLAGS = ["--headless=new", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox",
         "--disable-background-networking", "--disable-component-update", "--no-first-run"]
LOCAL_SCHEMES = ("file:", "data:", "blob:", "about:")


@pytest.fixture(scope="module")
def refine_page(tmp_path_factory, capture_dir):
    root = tmp_path_factory.mktemp("page")
    t0 = time.perf_counter()
    assert main(["--quiet", "refine", str(capture_dir), str(root / "refined"), *TINY_SOLVER]) == 0
    print(f"refine with its page: {time.perf_counter() - t0:.1f} s")
    return root / "refined" / REPORT_HTML


@pytest.fixture(scope="module")
def reconstruct_page(tmp_path_factory):
    root = tmp_path_factory.mktemp("ring")
    capture, _ = render_ring("bunny", frames=6, size=(96, 72), scale_factor=2, arc_deg=120)
    write_capture(capture, root / "capture")
    assert main(["--quiet", "reconstruct", str(root / "capture"), str(root / "object"), "--depth", "raw",
                 "--references", "2", "--texture-px", "0", "--voxel-mm", "4"]) == 0
    return root / "object" / REPORT_HTML


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).is_file():
        pytest.fail(f"{CHROMIUM} is missing: install Debian's chromium ('make setup' does, as root; or "
                    "'sudo apt-get install chromium')")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        chromium = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS, headless=True)
        yield chromium
        chromium.close()


def open_page(browser, path: Path):
    """(page, console errors, requests to anything but the page's own file and inline data)."""
    page = browser.new_page(viewport={"width": 1200, "height": 900})
    errors, remote = [], []
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("request", lambda r: remote.append(r.url) if not r.url.startswith(LOCAL_SCHEMES) else None)
    page.goto(path.as_uri(), wait_until="load")
    return page, errors, remote


def canvas_pixels(page, timeout_s: float = 30.0) -> np.ndarray:
    """The 3D view's canvas as (H, W, 3) pixels, once it has drawn something (or at the timeout)."""
    frame = page.frame_locator("iframe.viewer")
    canvas = frame.locator("canvas")
    canvas.wait_for(timeout=timeout_s * 1000)
    page.locator("iframe.viewer").scroll_into_view_if_needed()
    deadline = time.perf_counter() + timeout_s
    while True:
        pixels = np.asarray(Image.open(io.BytesIO(canvas.screenshot())).convert("RGB"), dtype=np.float64)
        if pixels.std() > 0 or time.perf_counter() > deadline:
            return pixels
        page.wait_for_timeout(250)


def check_page(browser, path: Path, min_images: int) -> None:
    page, errors, remote = open_page(browser, path)
    widths = page.evaluate("Array.from(document.images).map(i => i.complete ? i.naturalWidth : 0)")
    pixels = canvas_pixels(page)
    page.wait_for_timeout(300)  # late console messages of the viewer
    assert errors == [], f"console errors on {path.name}: {errors}"
    assert remote == [], f"{path.name} asked the network for {remote}"
    assert len(widths) >= min_images and all(w > 0 for w in widths), f"images not decoded: {widths}"
    # the mesh (coloured, shaded) on a white background: many distinct colours, not a blank canvas
    assert pixels.shape[0] > 100 and pixels.shape[1] > 100
    assert pixels.std() > 5.0, "the 3D canvas is blank"
    assert np.mean(pixels.sum(axis=2) < 3 * 250) > 0.01, "nothing but background in the 3D canvas"


def test_refine_page_loads_offline_with_figures_and_a_3d_view(browser, refine_page):
    t0 = time.perf_counter()
    # normals (input, refined, difference), albedo + depth, lighting, residual, energy, poses
    check_page(browser, refine_page, min_images=6)
    print(f"browser check: {time.perf_counter() - t0:.1f} s, page {refine_page.stat().st_size / 1e6:.2f} MB")


def test_reconstruct_page_loads_offline_with_a_3d_view(browser, reconstruct_page):
    check_page(browser, reconstruct_page, min_images=0)
    text = reconstruct_page.read_text()
    assert "Reference views" in text and "the back of the mesh is missing" in text  # a 120-degree arc
    assert "degrees around the object: the mesh holds what they saw" in text  # reconstruct's warning, caught


def test_page_is_self_contained(refine_page):
    text = refine_page.read_text()
    for attribute in ('src="http', "src='http", 'href="http', "href='http"):
        assert attribute not in text
    assert "kitware.github.io/vtk-js/icon" not in text  # the viewer's favicons, pointed at an inline image
    report = json.loads((refine_page.parent / "report.json").read_text())
    assert report["method"] == "ours"


def test_contract_sections_appear_when_present(refine_page):
    # The report.json keys other engineers fill (frames_report, inputs, pose_updates, pose_steps,
    # residuals, warnings) show as tables and plots; absent ones are left out (the page above has none).
    from o3d_mvps.refinement import read_refinement

    refinement = read_refinement(refine_page.parent)
    info = {"frames": [0, 1, 2],
            "frames_report": [{"index": 0, "file": "color/000000.png", "used": True, "reason": None},
                              {"index": 3, "file": "color/000003.png", "used": False, "reason": "blurred frame"}],
            "inputs": {"checks": [{"name": "depth_scale", "status": "warning", "detail": "depth looks like cm"}],
                       "conventions": {"pose": "reference -> frame i"}},
            "pose_updates": [{"frame": 1, "moved_mm": 1.5, "moved_deg": 0.2, "rejected_updates": 0, "note": None},
                             {"frame": 2, "moved_mm": 9.0, "moved_deg": 1.1, "rejected_updates": 2,
                              "note": "kept the odometry pose"}],
            "residuals": [{"frame": 0, "rms": 0.01}, {"frame": 1, "rms": 0.02}, {"frame": 2, "rms": 0.03}],
            "pose_steps": [[1, 22259, "joint"], [0, 89512, "held"]]}
    report = {"method": "ours", "energy": [], "timings": {"total": 1.0}, "info": info,
              "warnings": ["frame 3 dropped: blurred frame"]}
    text = report_page_html(report, refinement=refinement)
    for expected in ("color/000003.png", "blurred frame", "depth looks like cm", "reference -&gt; frame i",
                     "kept the odometry pose", 'alt="per-frame RMS residual"', "frame 3 dropped",
                     "joint pose-depth steps", "held: settled by a coarser level&#x27;s joint steps", "89512"):
        assert expected in text, expected
    bare = report_page_html({"method": "ours"}, refinement=refinement)
    assert "Input checks" not in bare and "per-frame RMS residual" not in bare and "Warnings" in bare


def test_show_mesh_is_the_viewer_or_a_static_image(refine_page, monkeypatch):
    from o3d_mvps.refinement import read_refinement
    from o3d_mvps.report_page import show_mesh

    mesh = read_refinement(refine_page.parent).to_mesh()
    viewer = show_mesh(mesh, interactive=True)
    assert "<iframe" in viewer.data and "OfflineLocalView" in viewer.data and "kitware.github.io/vtk-js/icon" not in viewer.data
    monkeypatch.setenv("CI", "1")  # where no browser looks: a PNG
    image = show_mesh(mesh, size=(160, 120))
    pixels = np.asarray(Image.open(io.BytesIO(image.data)).convert("RGB"))
    assert pixels.shape == (120, 160, 3) and pixels.std() > 5.0


def test_page_mesh_is_a_strided_grid_of_the_refined_depth_within_the_budget():
    # A 200x150 bump, every pixel in the mask: 30k pixels, ~60k triangles meshed at full resolution.
    # Budget 5000 -> stride ceil(sqrt(2 * 30000 / 5000)) = 4; each vertex is a full-resolution
    # pixel (4u', 4v') back-projected (no quadric decimation moving it).
    from o3d_mvps import Refinement
    from o3d_mvps.report_page import page_mesh

    K = np.array([[250.0, 0, 99.5], [0, 250.0, 74.5], [0, 0, 1]])
    v, u = np.mgrid[0:150, 0:200].astype(float)
    depth = 0.6 - 0.05 * np.exp(-((u - 100) ** 2 + (v - 75) ** 2) / 800.0)
    refinement = Refinement.from_arrays(depth, np.ones((150, 200), bool), K, albedo=np.full((150, 200, 3), 0.5))
    mesh, stride = page_mesh(refinement, max_triangles=5000)
    assert stride == 4
    positions = mesh.vertex.positions.numpy().astype(np.float64)
    assert 0 < len(mesh.triangle.indices) <= 5000
    pu = K[0, 0] * positions[:, 0] / positions[:, 2] + K[0, 2]
    pv = K[1, 1] * positions[:, 1] / positions[:, 2] + K[1, 2]
    assert np.allclose(pu / 4, np.round(pu / 4), atol=1e-3) and np.allclose(pv / 4, np.round(pv / 4), atol=1e-3)
    iu, iv = np.round(pu).astype(int), np.round(pv).astype(int)
    assert np.allclose(positions[:, 2], depth[iv, iu], atol=1e-6)  # float32 positions
    assert page_mesh(refinement, max_triangles=10**6)[1] == 1  # within the budget: every pixel
    text = report_page_html({"method": "ours"}, refinement=refinement)
    assert "meshed from one pixel in 2 along each row and column" in text  # 30k pixels, 40k triangles at most


def _scene(viewer: str) -> str:
    """The vtk.js scene a viewer page carries (index.json of its inline archive), with VTK's
    per-process instance addresses numbered in order of appearance and its modification
    counters zeroed, and its data arrays."""
    import base64
    import re
    import zipfile

    archive = re.search(r'base64Str = "([A-Za-z0-9+/=]+)"', viewer).group(1)  # vtksz2html's inline archive
    index = json.loads(zipfile.ZipFile(io.BytesIO(base64.b64decode(archive))).read("index.json"))
    ids = {}
    scene = re.sub(r'(instance:\$\{|"id": "|"parent": "|"camera": "|"vtkRefId": ")([0-9a-f]+)',
                   lambda m: m.group(1) + ids.setdefault(m.group(2), f"id{len(ids)}"),
                   json.dumps(index["scene"], sort_keys=True))
    scene = re.sub(r'"mtime": \d+', '"mtime": 0', scene)  # VTK's modification counters: a render bumps them
    return scene, {h: e["content"] for h, e in index["hashes"].items()}


def test_viewer_scene_needs_no_render(refine_page, monkeypatch):
    """The 3D view is serialised without rendering the window first (an OpenGL context and its
    shaders, 0.12 CPU s the first time in a process): the scene and arrays equal a rendered one's
    (a headlight left where no render placed it would differ)."""
    import trame_vtk.modules.vtk.serializers as serializers

    from o3d_mvps.refinement import read_refinement
    from o3d_mvps.report_page import mesh_viewer_html, page_mesh

    mesh, _ = page_mesh(read_refinement(refine_page.parent))
    plain, _, shown = mesh_viewer_html(mesh)
    serialize = serializers.serialize

    def rendered_first(parent, window, *args):
        window.Render()
        return serialize(parent, window, *args)

    monkeypatch.setattr(serializers, "serialize", rendered_first)
    rendered, _, _ = mesh_viewer_html(mesh)
    (scene, arrays), (scene_r, arrays_r) = _scene(plain), _scene(rendered)
    assert shown > 0 and len(arrays) >= 3
    assert scene == scene_r and arrays == arrays_r
