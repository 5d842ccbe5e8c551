#!/usr/bin/env python3
"""A simulated robot for the demo: a point on a plane, like turtlesim's turtle without the window.

Subscribes ``cmd_vel`` (geometry_msgs/Twist: linear.x forward speed, angular.z turn rate) and publishes its
``pose`` (geometry_msgs/Pose2D) at ``~rate`` Hz, integrating the last command. A command older than
``~cmd_timeout`` seconds is treated as stop, as real robot bases do.
"""

import math

import rospy
from geometry_msgs.msg import Pose2D, Twist


class SimRobot:
    def __init__(self, cmd_timeout):
        self.pose = Pose2D()
        self.cmd = Twist()
        self.cmd_stamp = None
        self.cmd_timeout = cmd_timeout

    def on_cmd_vel(self, msg):
        self.cmd = msg
        self.cmd_stamp = rospy.get_time()

    def step(self, dt, now):
        if self.cmd_stamp is None or now - self.cmd_stamp > self.cmd_timeout:
            return
        self.pose.theta = math.atan2(math.sin(self.pose.theta + self.cmd.angular.z * dt),
                                     math.cos(self.pose.theta + self.cmd.angular.z * dt))
        self.pose.x += self.cmd.linear.x * math.cos(self.pose.theta) * dt
        self.pose.y += self.cmd.linear.x * math.sin(self.pose.theta) * dt


def main():
    rospy.init_node("sim_robot")
    rate_hz = float(rospy.get_param("~rate", 10.0))
    robot = SimRobot(float(rospy.get_param("~cmd_timeout", 1.0)))
    rospy.Subscriber("cmd_vel", Twist, robot.on_cmd_vel, queue_size=1)
    pub = rospy.Publisher("pose", Pose2D, queue_size=1)
    rate = rospy.Rate(rate_hz)
    rospy.loginfo("sim_robot: publishing %s at %.0f Hz, obeying %s",
                  rospy.resolve_name("pose"), rate_hz, rospy.resolve_name("cmd_vel"))
    while not rospy.is_shutdown():
        robot.step(1.0 / rate_hz, rospy.get_time())
        pub.publish(robot.pose)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


if __name__ == "__main__":
    main()
