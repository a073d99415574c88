"""inkdiag_ros: thin rclpy nodes around inkdiag_core and msg_defs."""
