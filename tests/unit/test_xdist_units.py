"""The xdist work units tests/conftest.py hands out first still exist: a renamed file or group would
otherwise quietly drop out of FIRST_UNITS and the system tier's workers would go back to ending ~27 s apart."""

from __future__ import annotations

from tests.conftest import FIRST_UNITS, REPO_ROOT, SHARED_FIXTURE_GROUPS


def test_every_first_unit_is_a_shared_fixture_group_or_a_test_file():
    for unit in FIRST_UNITS:
        assert unit in SHARED_FIXTURE_GROUPS.values() or (REPO_ROOT / unit).is_file(), unit
