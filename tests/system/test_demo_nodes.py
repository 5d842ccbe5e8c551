"""The demo's own ROS nodes: the simulated robot moves when the brain drives it, and stands still otherwise."""


from tests.support.polling import wait_until


def _pose(master, topic):
    """Read one geometry_msgs/Pose2D from ``topic`` with a short-lived rospy subscription in a child."""
    import subprocess
    out = subprocess.run(["/usr/bin/rostopic", "echo", "-n", "1", topic], env=master.env(),
                         capture_output=True, text=True, timeout=20)
    values = {}
    for line in out.stdout.splitlines():
        if ":" in line:
            key, value = line.split(":", 1)
            values[key.strip()] = float(value)
    return values


def test_sim_robot_circles_when_the_brain_drives_it(procs, ros_master):
    env = ros_master.env()
    procs.start(["/usr/bin/rosrun", "robotics_demo", "sim_robot.py", "__ns:=demo_bot"], env=env, name="sim_robot")
    wait_until(lambda: "/demo_bot/pose" in ros_master.topic_types(), timeout=20, message="/demo_bot/pose")
    still = _pose(ros_master, "/demo_bot/pose")
    assert still == {"x": 0.0, "y": 0.0, "theta": 0.0}

    procs.start(["/usr/bin/rosrun", "robotics_demo", "patrol_brain.py", "__ns:=demo_bot"], env=env, name="brain")
    moved = wait_until(lambda: (lambda p: p if p.get("x", 0.0) > 0.05 else None)(_pose(ros_master, "/demo_bot/pose")),
                       timeout=30, message="the robot to move forward")
    assert moved["theta"] > 0.0  # it turns left, as the brain's positive angular.z asks
    assert ros_master.topic_types()["/demo_bot/cmd_vel"] == "geometry_msgs/Twist"
