"""The parameter tables in ``docs/*.md``, generated from the settings of the config dataclasses
(``volcap_core.settings``), so the documentation cannot drift from the code.

A table sits between two markers naming the config classes it lists, in order:

    <!-- parameters volcap_filter.session:DepthFilterNodeConfig volcap_filter.pipeline:DepthFilterConfig -->
    ...generated...
    <!-- end parameters -->

    python -m volcap_bringup.docs [--check] [DOCS_DIR]
"""
from __future__ import annotations

import argparse
import re
import sys
from importlib import import_module
from pathlib import Path

from volcap_core.settings import markdown_table

BLOCK = re.compile(r'(<!-- parameters ([^>]*?) -->\n)(.*?)(<!-- end parameters -->)', re.S)
DOCS = Path(__file__).resolve().parents[3] / 'docs'


def table(specs: str) -> str:
    """One table of every setting of the named classes (``module:Class`` separated by spaces)."""
    rows = []
    for spec in specs.split():
        module, _, name = spec.partition(':')
        lines = markdown_table(getattr(import_module(module), name)).splitlines()
        rows += lines if not rows else lines[2:]
    return '\n'.join(rows) + '\n'


def render(text: str) -> str:
    return BLOCK.sub(lambda m: m.group(1) + table(m.group(2)) + m.group(4), text)


def stale(docs: Path = DOCS) -> list[Path]:
    """The pages whose tables differ from the code."""
    return [p for p in sorted(docs.glob('*.md')) if render(p.read_text()) != p.read_text()]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog='python -m volcap_bringup.docs', description=__doc__.splitlines()[0])
    p.add_argument('docs', nargs='?', default=str(DOCS), help='the docs folder')
    p.add_argument('--check', action='store_true', help='only report pages whose tables are stale (exit 1)')
    args = p.parse_args(argv)
    pages = stale(Path(args.docs))
    if args.check:
        for page in pages:
            print(f'{page}: parameter tables differ from the code; run python -m volcap_bringup.docs')
        return 1 if pages else 0
    for page in pages:
        page.write_text(render(page.read_text()))
        print(f'updated {page}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
