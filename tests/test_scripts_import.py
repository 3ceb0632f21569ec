"""Every script in scripts/ still imports: they reach into the package (private helpers
included), and a module move that breaks one would otherwise go unnoticed until someone runs
it. Importing runs no script (each runs its work under ``if __name__ == "__main__"``)."""

from __future__ import annotations

import pytest
from conftest import ROOT, load_script

SCRIPTS = sorted(p.stem for p in (ROOT / "scripts").glob("*.py"))


def test_there_are_scripts_to_check():
    assert {"bench", "compare_pyfm", "partial_unseen", "evaluate"} <= set(SCRIPTS)


@pytest.mark.parametrize("name", SCRIPTS)
def test_script_imports(name):
    mod = load_script(name)
    assert callable(getattr(mod, "main", None)), f"scripts/{name}.py has no main()"
