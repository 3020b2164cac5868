"""matplotlib for the evaluations' figures: an optional dependency (the ``eval`` extra).

The core install (``pip install lino-loc``) runs the service and every evaluation that prints
numbers; drawing a figure needs matplotlib, installed by ``pip install 'lino-loc[eval]'``.
:func:`pyplot` returns ``matplotlib.pyplot`` on the non-interactive Agg backend, or raises
:class:`lino_loc.errors.LinoLocError` with one line naming the extra (the CLI prints it and
exits with status 2). A command that will plot calls it before its long computation.
"""

from __future__ import annotations

from typing import Any

from lino_loc.errors import LinoLocError

EXTRA = "eval"
INSTALL_HINT = f"pip install 'lino-loc[{EXTRA}]'"


def pyplot() -> Any:
    """``matplotlib.pyplot`` with the Agg backend; LinoLocError naming the extra if missing."""
    try:
        import matplotlib
    except ImportError:
        raise LinoLocError(f"plotting needs matplotlib, which is not installed: {INSTALL_HINT}") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
