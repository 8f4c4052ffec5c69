#!/usr/bin/env bash
# The project's one test command: installs what the tests need, checks the import boundaries, runs the suite.
set -euo pipefail
cd "$(dirname "$0")/.."
# A CPU build of torch first: a range alone could pull the registry's multi-GB CUDA build.
python -c "import torch" 2>/dev/null || python -m pip install -q "torch==2.13.0"
python -m pip install -q -e ".[test]"
bash tools/check_imports.sh
python -m pytest "$@"
