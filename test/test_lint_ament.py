"""The ament linters, for colcon users (`colcon test`); `make test` runs ruff with one config."""

import pytest


@pytest.mark.linter
def test_flake8():
    main = pytest.importorskip('ament_flake8.main').main_with_errors
    rc, errors = main(argv=[])
    assert rc == 0, f'{len(errors)} flake8 errors'


@pytest.mark.linter
def test_pep257():
    main = pytest.importorskip('ament_pep257.main').main
    assert main(argv=['.', 'test']) == 0
