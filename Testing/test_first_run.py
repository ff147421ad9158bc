"""What a new user meets first on the command line: --version, build's examples, the hint for
labels written apart."""

from mdlshapemodel.version import __version__

from common import run_cli


def test_version():
    result = run_cli("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"mdlshapemodel {__version__}"


def test_build_help_ends_with_examples():
    text = run_cli("build", "--help").stdout
    examples = text[text.index("examples:"):]
    assert "mdlshapemodel build labels/ -o out --label 1,2" in examples
    assert text.rstrip().endswith("(after an interruption)")


def test_labels_written_apart_get_the_comma_hint(tmp_path):
    result = run_cli("build", tmp_path, "--label", "1", "2", "-o", tmp_path / "out")
    assert result.returncode == 2
    assert "write --label 1,2" in result.stderr
    assert not (tmp_path / "out").exists()
    other = run_cli("build", tmp_path, "-o", tmp_path / "out", "--bogus", "3")
    assert other.returncode == 2 and "unrecognized arguments: --bogus 3" in other.stderr
