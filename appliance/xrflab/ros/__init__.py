"""ROS 2 side of XRF Lab: the ``xrf2_msgs`` interface package and the ``ros_xeno_bridge`` node.

``interfaces`` builds a real ROS 2 interface package from a project's ``msg/`` folder (no rclpy
needed for that); ``bridge`` is the rclpy node. Import rclpy only through ``bridge``.
"""
