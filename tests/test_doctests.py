"""The Examples sections of the docstrings run as written and print what they say."""

import doctest
import importlib
import pkgutil

import pytest

import colorps

MODULES = sorted(name for _, name, _ in pkgutil.walk_packages(colorps.__path__, "colorps."))


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{result.failed} docstring example(s) of {name} failed"


def test_examples_exist_where_users_start():
    """The entry points a user reads first carry an example that is run above."""
    finder = doctest.DocTestFinder()
    for obj in (colorps.reconstruct, colorps.Options, colorps.Reason, colorps.BucketGrid,
                colorps.compute_signatures, colorps.angular_error):
        assert any(t.examples for t in finder.find(obj)), obj.__name__
