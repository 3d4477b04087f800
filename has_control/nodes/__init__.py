"""The ROS 2 layer: thin nodes over the numerical core (nodes → tuning → core).

Nothing outside this package imports rclpy.
"""
