"""torchsoil as a live ROS node (`torchsoil node`): one body (torchsoil.node.body), a thin
transport for ROS 1 (rospy) and one for ROS 2 (rclpy)."""
