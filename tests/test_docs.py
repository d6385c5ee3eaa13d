"""The documentation site builds with warnings as errors (mkdocs --strict: broken links, pages
missing from the nav, docstrings mkdocstrings cannot render) and without the network: the build
runs with every socket connection refused. The generated CLI page has every subcommand."""

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from o3d_mvps.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
NO_NETWORK = textwrap.dedent("""
    import socket
    def _refuse(self, *args, **kwargs):
        raise OSError("network access during the docs build")
    socket.socket.connect = _refuse
    socket.socket.connect_ex = _refuse
    socket.create_connection = lambda *args, **kwargs: _refuse(None)
""")


def build(site: Path, config: Path = REPO / "mkdocs.yml") -> subprocess.CompletedProcess:
    """``mkdocs build --strict`` of ``config`` into ``site``, sockets refused (a sitecustomize)."""
    blocker = site.parent / "no_network"
    blocker.mkdir(exist_ok=True)
    (blocker / "sitecustomize.py").write_text(NO_NETWORK)
    env = {"PYTHONPATH": str(blocker), "NO_MKDOCS_2_WARNING": "1", "PATH": "/usr/bin:/bin", "HOME": str(site.parent)}
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(config),
                           "--site-dir", str(site)], capture_output=True, text=True, cwd=REPO, env=env, timeout=300)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    site = tmp_path_factory.mktemp("docs") / "site"
    done = build(site)
    assert done.returncode == 0, done.stderr[-3000:]
    return site


def test_cli_page_has_every_subcommand(site):
    page = (site / "cli" / "index.html").read_text()
    subcommands = next(a for a in build_parser()._actions if hasattr(a, "choices") and a.choices).choices
    assert {"demo", "render", "refine", "reconstruct", "export", "record", "convert"} <= set(subcommands)
    for name in subcommands:
        assert f"o3d-mvps {name}" in page and f"usage: o3d-mvps {name}" in page, name


def test_pages_and_plots_are_in_the_site(site):
    for page in ("getting-started", "capture-guide", "method", "benchmarks", "api", "gpu", "changelog"):
        assert (site / page / "index.html").is_file(), page
    assert (site / "results" / "scaling.png").stat().st_size > 10_000  # served from benchmarks/results
    api = (site / "api" / "index.html").read_text()
    assert "RefineOptions" in api and "printable_solid" in api and "reconstruct" in api
    index = (site / "index.html").read_text()
    assert "fonts.googleapis" not in index and "fonts.gstatic" not in index  # theme.font: false


def test_a_broken_link_fails_the_build(tmp_path):
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "index.md").write_text("# Home\n\n[nowhere](missing.md)\n")
    config = tmp_path / "mkdocs.yml"
    config.write_text("site_name: t\ndocs_dir: docs\ntheme:\n  name: material\n  font: false\n")
    done = build(tmp_path / "site", config)
    assert done.returncode != 0 and "missing.md" in done.stderr
