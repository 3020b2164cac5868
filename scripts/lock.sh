#!/usr/bin/env bash
# Write requirements/robot.lock: the exact versions of the core install (`pip install .`,
# no extras), resolved in a clean, temporary virtual environment by the interpreter that
# will run the daemon (PYTHON, default python3). Run it on the robot's Python version and
# architecture (wheels differ; the versions seldom do), commit the file, and install with
#   pip install -r requirements/robot.lock && pip install --no-deps .
# (docs/install.md). tests/test_lock_file.py checks that it lists every core dependency of
# pyproject.toml at a version that satisfies it.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="${PYTHON:-python3}"
out="$root/requirements/robot.lock"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$py" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install -q --upgrade pip
# a copy of the checkout: the build must not leave build/ or *.egg-info in it
cp -r "$root/pyproject.toml" "$root/README.md" "$root/lino_loc" "$root/drivers" "$root/services" \
      "$root/config" "$tmp/"
"$tmp/venv/bin/python" -m pip install -q "$tmp"
mkdir -p "$(dirname "$out")"
{
    echo "# The core install of lino-loc, exact versions: written by scripts/lock.sh, do not edit."
    echo "# $("$tmp/venv/bin/python" -c 'import platform, sys; print(f"Python {platform.python_version()} on {sys.platform} {platform.machine()}")')"
    echo "# Install: pip install -r requirements/robot.lock && pip install --no-deps ."
    "$tmp/venv/bin/python" -m pip freeze --exclude lino-loc --exclude pip --exclude setuptools --exclude wheel \
        | LC_ALL=C sort -f
} > "$out"
echo "wrote $out ($(grep -vc '^#' "$out") packages)"
