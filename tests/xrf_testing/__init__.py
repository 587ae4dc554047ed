"""Helpers shared by the test suites, imported as `xrf_testing.<module>`: tests/ is on the path
through pyproject.toml's `[tool.pytest.ini_options] pythonpath` (docs/developers/testing.md).
A few of its modules are also programs run by path (serve_for_test.py, fresh_run.py, journey.py)."""
