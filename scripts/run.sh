#!/usr/bin/env bash
# Set up (first time) and run the localization service. With no configuration and no robot
# attached, `lino-loc run` starts the simulated robot and builds its map once (cached).
# Extra arguments go to `lino-loc run` (e.g. --config config/lino.toml on the robot).
source "$(dirname "$0")/_venv.sh"
exec lino-loc run "$@"
