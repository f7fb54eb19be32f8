"""Record and replay: rosbag2 bags of flights (bag_record, bag_play, replay_assist, plot_flight).

Containers and CDR come from `rosbags` (the only library among rosbags, mcap and mcap-ros2-support
that read every real bag of ros2/rosbag2's test resources, mcap and sqlite3; see README "Bags").
Pure cores here import no rclpy; record_node and play_node are the thin ROS shells.
"""
