"""The documentation stands on its own: every document the code, the help and the results point to is in the
repository, and every link between the documents resolves."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from spadscan.commands import baseline, reconstruct
from spadscan.dashboard.results import PAGES
from spadscan.worker.report.view3d import VIEW3D

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


def _results_table() -> str:
    """docs/job_queue.md's table of the files a job publishes (its "## Results" section)."""
    text = (ROOT / "docs" / "job_queue.md").read_text()
    return text[text.index("\n## Results"):]


def _readme_step(number: int) -> str:
    """Step `number` of the README's lab workflow ("Using it in the lab"), up to the next step."""
    return re.search(rf"\n{number}\. \*\*.*?(?=\n\d+\. \*\*|\n## )", (ROOT / "README.md").read_text(), re.S)[0]


def test_every_result_file_the_dashboard_links_is_listed_where_results_are():
    """Someone who copies or archives the files the docs list keeps every one the dashboard and report.html open
    (view3d.html, the report's 3D view, among them)."""
    from spadscan.commands import baseline, reconstruct
    from spadscan.dashboard.results import PAGES
    from spadscan.worker.report.view3d import VIEW3D

    for where, text in [("docs/job_queue.md results", _results_table()), ("README step 6", _readme_step(6)),
                        ("spadscan reconstruct --help", reconstruct.__doc__)]:
        missing = [name for name in PAGES if name not in text]
        assert not missing, f"{where} does not list {missing}"
    assert VIEW3D in baseline.__doc__, "spadscan baseline --help does not list the 3D view it writes"


def _captures_of_the_example_configs() -> set[str]:
    return {tomllib.loads(p.read_text())["captures"] for p in sorted((ROOT / "examples").glob("rig-*.toml"))}


def test_the_worker_watches_the_folder_the_example_configs_write_to():
    """The worker unit and the README's lab workflow point the worker at the example rig configs' captures folder
    (with ~ as the unit user's home: systemd expands no ~), so that the scans the daemon writes are reconstructed."""
    unit = (ROOT / "examples" / "systemd" / "spadscan-worker.service").read_text()
    (captures,) = _captures_of_the_example_configs()
    (user,) = re.findall(r"^User=(\S+)$", unit, re.M)
    (exec_start,) = re.findall(r"^ExecStart=(.*)$", unit, re.M)
    (root,) = re.findall(r"--root (\S+)", exec_start)
    assert root == captures.replace("~", f"/home/{user}", 1) and root.startswith("/"), (root, captures)
    roots = re.findall(r"spadscan worker --root ([~/]\S*?)`", _readme_step(6))
    assert roots and all(r.replace("~", f"/home/{user}", 1) == root for r in roots), roots


def _two_commands() -> str:
    """The README's install and test section ("Two commands"), up to the next paragraph that is not about it."""
    return re.search(r"\n## Two commands\n(.*?)\*\*On a GPU:\*\*", (ROOT / "README.md").read_text(), re.S)[1]


def test_the_readme_says_what_the_test_command_installs_outside_python():
    """tests/run.sh apt-installs system packages when run as root: a user running it in a container or as root on a
    lab PC is told so where the command is given, package by package."""
    run_sh = (ROOT / "tests" / "run.sh").read_text()
    assert "apt-get install" in run_sh
    packages = set(re.findall(r"missing\+=\(([^)]*)\)", run_sh))
    packages = {name for group in packages for name in group.split()}
    assert packages, "tests/run.sh installs no system package: drop this test and the README's note"
    section = _two_commands()
    assert "root" in section and "apt-get" in section, section
    assert all(f"`{name}`" in section for name in packages), (packages, section)


def test_pyproject_says_what_the_test_command_does_about_torch():
    """run.sh installs torch from pip's default index (the CUDA build on Linux), never the CPU build: the comment
    by the torch dependency must not promise that it does, as the README does not."""
    run_sh = (ROOT / "tests" / "run.sh").read_text()
    (install,) = re.findall(r"pip install -q \"torch[^\n]*", run_sh)
    assert "--index-url" not in install and "+cpu" not in install, install
    text = (ROOT / "pyproject.toml").read_text()
    comment = " ".join(line.strip().lstrip("# ") for line in re.findall(r"^\s*#.*$", text, re.M))
    assert "tests/run.sh installs that build" not in comment, comment
    assert "tests/run.sh installs torch only where there is none" in comment, comment
