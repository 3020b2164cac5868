"""The research harness is optional: without matplotlib (the ``eval`` extra) the service's
modules load and a plotting evaluation fails at once with one line naming the extra."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NO_MATPLOTLIB = "import sys; sys.modules['matplotlib'] = None; sys.modules['matplotlib.pyplot'] = None\n"


def _python(code: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1", DEPTHAI_LEVEL="error")
    return subprocess.run([sys.executable, "-c", NO_MATPLOTLIB + code], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=60)


@pytest.mark.parametrize("command", [["active", "--positions", "1", "--runs", "1"], ["sensor-model"]])
def test_plotting_without_the_extra_is_one_line_naming_it(tmp_path, command) -> None:
    argv = ["eval", *command, "--plot", str(tmp_path / "figs")]
    res = _python(f"from services.cli import main; sys.exit(main({argv!r}))")
    assert res.returncode == 2, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    assert "pip install 'lino-loc[eval]'" in lines[0] and "Traceback" not in res.stderr
    assert not (tmp_path / "figs").exists()  # it failed before doing any work


def test_the_daemon_and_the_cli_load_without_matplotlib_or_the_evaluations() -> None:
    res = _python(
        "import services.commands.run, services.daemon, services.sim_launcher\n"
        "assert not any(m == 'services.evaluation' or m.startswith('services.evaluation.') for m in sys.modules)\n"
        "from services.cli import build_parser\n"
        "args = build_parser().parse_args(['run'])\n"
        "print('ok')\n"
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "ok"


def test_pyplot_with_matplotlib_uses_agg() -> None:
    pytest.importorskip("matplotlib")
    from services.evaluation.plotting import pyplot

    plt = pyplot()
    assert plt.get_backend().lower() == "agg"
