#!/usr/bin/env bash
# Set up (first time) and run the whole test suite: lint, layering contracts, tests.
source "$(dirname "$0")/_venv.sh"
ruff check .
lint-imports
# Two workers by default (LINO_TEST_WORKERS=0: one process); whole files go to one worker, so a
# module's fixtures are built once.
python -m pytest -n "${LINO_TEST_WORKERS:-2}" --dist loadfile "$@"
