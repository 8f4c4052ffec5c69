#!/usr/bin/env bash
# The project's one test command: installs what the tests need, checks the import boundaries, runs the suite.
set -euo pipefail
cd "$(dirname "$0")/.."
# The pages' tests drive the system's Chromium (Playwright never downloads a browser here), and the mesh pictures
# draw through EGL without a display: install what is missing where we may (CI runs as root on Debian). Elsewhere
# the browser tests skip, saying why.
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    missing=()
    [ -x /usr/bin/chromium ] || missing+=(chromium)
    ldconfig -p | grep 'libEGL_mesa\.so' >/dev/null || missing+=(libegl1 libegl-mesa0)
    if [ "${#missing[@]}" -gt 0 ]; then
        { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null; } ||
            echo "tests/run.sh: could not install ${missing[*]}; the tests that need them skip or say why" >&2
    fi
fi
# torch only where none is installed, pinned, from pip's default index (on Linux its multi-GB CUDA build: install the
# CPU build first, as the README says, where that matters).
python -c "import torch" 2>/dev/null || python -m pip install -q "torch==2.13.0"
python -m pip install -q -e ".[test]"
bash tools/check_imports.sh
# Two test processes, each taking whole files (their module fixtures are built once): most tests wait on the
# processes they start, so two at once fit two cores. `-n 0` after the command runs everything in one process.
# (pytest-benchmark, where a machine has it, would only warn that it cannot time under xdist: none of ours uses it.)
python -m pytest -n 2 --dist loadfile -p no:benchmark "$@"
