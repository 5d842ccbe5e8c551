"""Unit tests of ``rcm`` (rcm_driver): its helpers and its agent server, in this process."""
