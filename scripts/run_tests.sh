#!/usr/bin/env bash
# Lint, then the whole test suite (pytest exit 5, "no tests collected", fails like any error).
set -euo pipefail
cd "$(dirname "$0")/.."
ruff check .
ruff format --check . >/dev/null || { ruff format --diff . | head -40; exit 1; }
exec python -m pytest "$@"
