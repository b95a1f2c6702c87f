"""SQLAlchemy is imported only where an index of runs is opened (``rigctl.record_index``):
the runner, every procedure and the CLI import without it, so a re-solve of a copied run
directory, ``rigctl procedures`` and ``rigctl sim`` do not pay for it (issue 43's
whole-process time); opening an index imports it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.mockproc import ROOT

SOLVE_PATH = """
import sys
import rigctl.cli, rigctl.runner, rigctl.records
from rigctl import procedures
for name in procedures.procedure_names():
    procedures.get_procedure(name)
print(sorted(m for m in sys.modules if m.split('.')[0] == 'sqlalchemy')[:3])
"""

OPENED = """
import sys
from rigctl.record_index import RecordIndex
RecordIndex('sqlite:///' + sys.argv[1])
print('sqlalchemy' in sys.modules)
"""


def _python(code: str, *args: str) -> str:
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                          timeout=120, cwd=ROOT)  # a hang guard, not a timing claim
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip()


@pytest.mark.timeout(240)
def test_the_cli_runner_and_procedures_import_without_sqlalchemy():
    assert _python(SOLVE_PATH) == "[]"


@pytest.mark.timeout(240)
def test_opening_an_index_imports_it(tmp_path):
    assert _python(OPENED, str(tmp_path / "index.sqlite")) == "True"
    assert (tmp_path / "index.sqlite").exists()
