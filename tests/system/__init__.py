"""Multi-process tests: each starts child processes (agents, ROS masters and nodes, brokers, browsers, OpenVPN,
network namespaces, the command-line tools). Every test here is marked ``slow`` (``tests/conftest.py``)."""
