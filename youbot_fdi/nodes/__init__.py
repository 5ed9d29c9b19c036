"""ROS 2 nodes: thin rclpy adapters over the core. The only package that imports rclpy."""
