#!/usr/bin/env python3
"""The demo's server-side brain: drives the simulated robot round a circle of radius ~radius.

Subscribes the robot's ``pose`` and publishes ``cmd_vel`` at 5 Hz: constant forward speed with the turn rate
that keeps the robot on the circle (speed / radius). It stays quiet until the robot's first pose arrives.
"""

import rospy
from geometry_msgs.msg import Pose2D, Twist


def main():
    rospy.init_node("patrol_brain")
    speed = float(rospy.get_param("~speed", 0.5))
    radius = float(rospy.get_param("~radius", 2.0))
    seen = {"pose": None}
    rospy.Subscriber("pose", Pose2D, lambda msg: seen.update(pose=msg), queue_size=1)
    pub = rospy.Publisher("cmd_vel", Twist, queue_size=1)
    rate = rospy.Rate(5)
    rospy.loginfo("patrol_brain: circling at %.2f m/s on a %.1f m circle", speed, radius)
    while not rospy.is_shutdown():
        if seen["pose"] is not None:
            cmd = Twist()
            cmd.linear.x = speed
            cmd.angular.z = speed / radius
            pub.publish(cmd)
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


if __name__ == "__main__":
    main()
