"""The test suite: unit tests and multi-process tests against real ROS masters, agents and HTTP servers."""
