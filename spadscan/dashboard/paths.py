"""Which files under the captures root the dashboard serves, and the URL paths that name them.

Both sides use this module: the server resolves a requested URL path with `safe_path`, and the indexes give the page
a link only where `safe_path` would serve it, so that the page never shows a link that answers 404.
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import quote, unquote


def url_path(*names: str) -> str:
    """Folder and file names joined into a percent-encoded URL path: a name may hold '#', '?', '%' or spaces (any
    folder a user or `spadscan simulate --out` made), which a browser would otherwise read as a fragment, a query or
    an escape. Undecodable bytes of a name (surrogate escapes) travel as their own %XX, which `safe_path` restores."""
    return "/".join(quote(name, safe="", errors="surrogateescape") for name in names)


def safe_path(root: Path, url_path: str) -> Path | None:
    """The file under `root` that `url_path` (percent-encoded, '/'-separated, relative to root) names, or None when
    it names anything outside the root (after '..' and links are resolved), a hidden component (in the URL or, after
    links are resolved, below the root) or no regular file."""
    parts = [p for p in unquote(url_path, errors="surrogateescape").split("/") if p not in ("", ".")]
    if not parts or any(p.startswith(".") or "\\" in p or "\x00" in p for p in parts):
        return None  # '..' starts with a dot too
    root = root.resolve()
    try:
        path = root.joinpath(*parts).resolve()
        # is_file() raises for a name the system refuses (ENAMETOOLONG over 255 bytes): that is no file, not a fault
        if root not in path.parents or not path.is_file():
            return None
        # a link inside the root may lead into a hidden folder (the queue, a job being written): refused as its own
        # name would be
        if any(p.startswith(".") for p in path.relative_to(root).parts):
            return None
    except (OSError, RuntimeError, ValueError):
        return None
    return path
