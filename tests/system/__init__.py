"""Tests that start child processes: real agents, ROS masters, brokers, browsers, network namespaces."""
