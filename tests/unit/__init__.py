"""Unit tests: in one process, no child processes. ``tests/unit/<package>/test_<module>[_<aspect>].py`` mirrors the
source tree (``tests/unit/test_<file>.py`` for a file at the root of the tree)."""
