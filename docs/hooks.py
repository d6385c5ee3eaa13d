"""mkdocs hooks: the command-line reference generated from ``o3d_mvps.cli.build_parser()``
(every subcommand's ``--help``), and the benchmark plots of ``benchmarks/results/`` served
under ``results/``, both added to the site at build time (nothing is written into docs/)."""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
#: a Sphinx role before inline code in a rendered docstring (``:func:`x``` becomes ``:func:<code>x</code>``)
SPHINX_ROLE = re.compile(r":(?:func|class|mod|meth|data|attr|exc):<code>~?([\w.]*?)([\w]+)</code>")


def cli_markdown() -> str:
    """docs/cli.md: the hand-written introduction, then ``o3d-mvps --help`` and every
    subcommand's help, as terminal text (80 columns)."""
    os.environ["COLUMNS"] = "80"  # argparse wraps to the terminal width: fix it for a stable page
    sys.path.insert(0, str(ROOT))
    from o3d_mvps.cli import build_parser

    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    parts = [(ROOT / "docs" / "cli_intro.md").read_text().rstrip(), "",
             "## o3d-mvps", "", "```text", parser.format_help().rstrip(), "```", ""]
    for name, sub in subparsers.choices.items():
        parts += [f"## o3d-mvps {name}", "", "```text", sub.format_help().rstrip(), "```", ""]
    return "\n".join(parts)


def on_files(files, config):
    """Add the generated CLI page and the benchmark plots to the site's files."""
    files.append(File.generated(config, "cli.md", content=cli_markdown()))
    for png in sorted(RESULTS.glob("*.png")):
        files.append(File.generated(config, f"results/{png.name}", abs_src_path=str(png)))
    return files


def on_page_content(html, page, config, files):
    """Docstrings use Sphinx roles (``:func:`~o3d_mvps.refine```); show them as plain code
    (the last name for ``~``-prefixed targets, as Sphinx does)."""
    return SPHINX_ROLE.sub(lambda m: f"<code>{m.group(2) if '~' in m.group(0) else m.group(1) + m.group(2)}</code>",
                           html)
