"""ROS 2 nodes of semfeat_ros: the only modules (with tools/) that import rclpy."""
