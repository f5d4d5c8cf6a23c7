"""ROS 2 (Jazzy rclpy) shell around the ROS-free core. The only package that imports rclpy."""
