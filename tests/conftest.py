"""Test settings: property-based tests explore the same examples on every run (derandomized,
no example database), so a test run is reproducible and CI sees what a developer saw."""

from hypothesis import settings

settings.register_profile("pporpe", derandomize=True, database=None, print_blob=True)
settings.load_profile("pporpe")
