"""Unit tests of the stand-in context broker (``tests/ngsi_broker``): one file per module."""
