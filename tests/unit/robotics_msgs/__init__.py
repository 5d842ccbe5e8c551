"""Unit tests of ``robotics_msgs``: the generated messages and service."""
