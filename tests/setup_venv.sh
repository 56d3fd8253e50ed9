#!/usr/bin/env bash
# Creates (or reuses) .venv with the pinned Python test dependencies. Prints the venv's python.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=.venv
stamp="$venv/.requirements.sha256"
want=$(sha256sum tests/requirements.txt | cut -d' ' -f1)
if [ ! -x "$venv/bin/python" ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    python3 -m venv "$venv" >&2
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r tests/requirements.txt >&2
    echo "$want" > "$stamp"
fi
echo "$PWD/$venv/bin/python"
