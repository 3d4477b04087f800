"""The sample loop without ROS: the plant and controller processes, their guards,
the ports of the two message layouts, and one :func:`~has_control.loop.schedule.run_loop`
with two timing policies (lock-step and paced).

The nodes (:mod:`has_control.nodes`) are thin shells over this wing, as
ros2/demos' lifecycle talker is over its publisher: they declare parameters,
create the topics, and hand the bytes that arrive to a process or a port. This
wing imports no rclpy; its tests run without it (test/test_loop.py).
"""
