"""Plain helpers shared by the tests: file writers, scenes, servers, polling.

Fixtures live in ``conftest.py`` files (where pytest finds them); everything else a test
module needs from elsewhere comes from here, so that no test module imports another.
"""
