"""The command line of one of spadscan's modules run as a child process, with this process's interpreter.

`python -m MODULE` puts the child's working folder first on its sys.path, ahead of the installed package. A folder
there named like one of ours is then imported in its place: run from the folder that holds a clone of the repository
(`~/spadscan`, no `__init__.py` at its top), `import spadscan` finds the clone as a namespace package instead of the
installed one, and the child fails on its first use of the package's contents (`spadscan.__version__`). `-P`
(Python >= 3.11, as pyproject requires) leaves the working folder off. PYTHONPATH still counts: a caller that means
the child to import something beside the package says so there.

Standard library only: every process that starts a child (the CLI, the demo, the daemon, the worker, the
benchmarks) imports it.
"""

from __future__ import annotations

import sys


def module_command(module: str, *args) -> list[str]:
    """`python -P -m MODULE ARGS...` with this interpreter; each argument as str (a Path, a number)."""
    return [sys.executable, "-P", "-m", module, *map(str, args)]
