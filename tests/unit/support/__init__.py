"""Unit tests of the test support (``tests/support``)."""
