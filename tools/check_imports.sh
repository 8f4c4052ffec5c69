#!/usr/bin/env bash
# Check the import-linter contracts in pyproject.toml. The editable install maps spadscan.protocol -> protocol/
# through an import hook that import-linter cannot walk, so lay the installed shape out in a temporary folder.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
mkdir -p "$tmp/spadscan"
cp -r "$repo"/spadscan/. "$tmp/spadscan/"
for part in protocol daemon worker; do cp -r "$repo/$part" "$tmp/spadscan/$part"; done
cp "$repo/pyproject.toml" "$tmp/"
cd "$tmp" && PYTHONPATH="$tmp" lint-imports --no-cache "$tmp/pyproject.toml"
