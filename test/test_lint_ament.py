"""The ament linters of `colcon test`, run by `make test` too (`make venv` installs them)."""

from ament_flake8.main import main_with_errors
from ament_pep257.main import main as pep257_main
import pytest


@pytest.mark.linter
def test_flake8():
    rc, errors = main_with_errors(argv=[])
    assert rc == 0, f'{len(errors)} flake8 errors'


@pytest.mark.linter
def test_pep257():
    assert pep257_main(argv=['.', 'test']) == 0
