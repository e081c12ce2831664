"""The public API: every name in ``labelaudit.__all__`` resolves, and its doctests pass."""

from __future__ import annotations


def test_every_public_name_resolves_and_the_doctests_pass():
    import doctest

    import labelaudit

    for name in labelaudit.__all__:
        assert getattr(labelaudit, name) is not None, name
    failures, tried = doctest.testmod(labelaudit)
    assert tried > 0 and failures == 0
