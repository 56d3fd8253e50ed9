#!/usr/bin/env bash
# The project's whole test command (README, .ci/run). Installs what it needs itself.
set -euo pipefail
cd "$(dirname "$0")/.."

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy"
cargo clippy --workspace --all-targets -- -D warnings
echo "== cargo test"
cargo test --workspace

echo "== python test environment"
python=$(bash tests/setup_venv.sh)

echo "== Cyphal interoperability (pycyphal)"
"$python" -m pytest tests/interop -q
