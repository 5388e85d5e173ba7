"""Test-wide settings: property tests draw the same examples on every run (CI is repeatable)."""

from hypothesis import settings

settings.register_profile('repeatable', derandomize=True)
settings.load_profile('repeatable')
