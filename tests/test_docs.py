"""The documentation stands on its own: every document the code, the help and the results point to is in the
repository, and every link between the documents resolves."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("spadscan", "daemon", "protocol", "worker", "tools", "benchmarks", "examples", "firmware_notes", "docs",
           "tests")
# Documents of the project's early design that never shipped with it: a reference to one leaves a user stranded.
OUTSIDE = re.compile(r"\bDESIG[N]\b|SENSOR_FACT[S]|STYLE\.md")  # [N], [S]: so that a grep for the names finds no file
DOC_PATH = re.compile(r"\bdocs/[\w./-]+\.md\b")
MD_LINK = re.compile(r"\]\(([^)#\s]+)(#[^)\s]*)?\)")


def text_files():
    yield ROOT / "README.md"
    for top in SOURCES:
        for path in sorted((ROOT / top).rglob("*")):
            if path.suffix in (".py", ".md", ".toml", ".sh", ".txt") and path.name != Path(__file__).name:
                yield path


def test_nothing_points_at_documents_outside_the_repository():
    found = [f"{p.relative_to(ROOT)}:{n}: {line.strip()}" for p in text_files()
             for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1) if OUTSIDE.search(line)]
    assert not found, "references to documents the project does not contain:\n" + "\n".join(found)


def test_every_docs_path_named_in_code_and_text_exists():
    missing = [f"{p.relative_to(ROOT)}: {m}" for p in text_files()
               for m in DOC_PATH.findall(p.read_text(errors="replace")) if not (ROOT / m).is_file()]
    assert not missing, "\n".join(missing)


def test_links_between_documents_resolve():
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "benchmarks" / "RESULTS.md"]
    broken = []
    for page in pages:
        for target, anchor in MD_LINK.findall(page.read_text()):
            if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
                continue
            dest = (page.parent / target).resolve()
            if not dest.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
            elif anchor and dest.suffix == ".md" and anchor[1:] not in _anchors(dest):
                broken.append(f"{page.relative_to(ROOT)}: {target}{anchor}")
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_the_docs_index_lists_every_page():
    index = (ROOT / "docs" / "README.md").read_text()
    pages = {p.name for p in (ROOT / "docs").glob("*.md")} - {"README.md"}
    assert pages and all(f"]({name})" in index for name in pages), sorted(pages)


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings: lower case, punctuation dropped, spaces to hyphens."""
    out = set()
    for line in page.read_text().splitlines():
        if line.startswith("#"):
            title = line.lstrip("#").strip().lower()
            out.add(re.sub(r"\s", "-", re.sub(r"[^\w\s-]", "", title)))
    return out
