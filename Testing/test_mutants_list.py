"""The mutation check's list (Testing/tools/mutants.py) stays aimed at the code: every planted
bug's original text occurs exactly once in its file, and every test file it names exists. A
mutant whose code moved or was rewritten would otherwise plant nothing and kill nothing."""

import importlib.util
import subprocess
import sys
from pathlib import Path

TOOL = Path(__file__).resolve().parent / "tools" / "mutants.py"


def load_tool():
    """The mutation check as a module (it is a script beside the tests, not a package)."""
    spec = importlib.util.spec_from_file_location("mutants", TOOL)
    module = importlib.util.module_from_spec(spec)
    sys.modules["mutants"] = module      # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


def test_every_mutant_of_the_list_is_found_in_the_code():
    """``mutants.py --list`` checks the whole list (and the test files of every mutant) against
    the package; it fails naming each mutant whose original text is gone."""
    result = subprocess.run([sys.executable, str(TOOL), "--list"], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 0, f"the mutation list has rotted:\n{result.stderr}"
    tool = load_tool()
    assert f"{len(tool.MUTANTS)} mutants" in result.stdout
    for mutant in tool.MUTANTS:
        assert mutant.name in result.stdout


def test_the_list_check_names_a_mutant_whose_text_is_gone():
    """The check behind ``--list`` names the mutant, the file and the problem: text that is not
    in the file, a test file that does not exist, a name used twice."""
    tool = load_tool()
    kept = tool.MUTANTS[0]
    gone = tool.Mutant("moved_away", kept.file, kept.original + " # no longer here",
                       kept.replacement, kept.tests, "a mutant of code that moved")
    missing_test = tool.Mutant("untested", kept.file, kept.original, kept.replacement,
                               ("test_no_such_file.py",), "a mutant of a test file that is gone")
    problems = tool.check([kept, gone, missing_test, kept], [missing_test])
    assert any(p.startswith("moved_away:") and "occurs 0 times" in p and kept.file in p
               for p in problems), problems
    assert any(p.startswith("untested:") and "test_no_such_file.py" in p for p in problems)
    assert any(p.startswith(f"{kept.name}:") and "used twice" in p for p in problems)
    assert not tool.check([kept], [kept])
