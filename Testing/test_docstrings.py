"""The Examples in the library's docstrings run and give what they show (doctest), so that the
documentation of the public functions cannot drift from the code."""

import doctest
import importlib
import pkgutil

import pytest

import mdlshapemodel

MODULES = sorted(name for _, name, _ in pkgutil.walk_packages(mdlshapemodel.__path__,
                                                               "mdlshapemodel."))


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    failed, _ = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert failed == 0
