"""Helpers shared by every test: free ports, polling with deadlines, owned child processes, ROS masters."""
