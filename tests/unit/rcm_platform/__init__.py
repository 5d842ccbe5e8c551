"""Unit tests of the agent, ``rcm_platform``: one file (or more, ``_<aspect>``) per module."""
