#!/usr/bin/env bash
# Set up (first time) and run the whole test suite: lint, layering contracts, tests.
source "$(dirname "$0")/_venv.sh"
ruff check .
lint-imports
python -m pytest "$@"
