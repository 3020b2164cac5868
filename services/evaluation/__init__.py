"""The research harness: the paper's experiments and the speed measurements on the simulated
robot and on datasets (``lino-loc eval ...``, ``lino-loc bench ...``; their command modules are
in :mod:`services.evaluation.commands`). The daemon never imports this package (an
import-linter contract in pyproject.toml); its figures need the ``eval`` extra (matplotlib)."""
