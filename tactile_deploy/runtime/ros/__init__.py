"""ROS 2 output of the runtime, with or without ROS installed.

* :mod:`.messages` builds standard ROS 2 messages (sensor_msgs/Image, sensor_msgs/PointCloud2,
  visualization_msgs/Marker, geometry_msgs/WrenchStamped) from a processed frame, as plain data
  (numpy only);
* :mod:`.convert` turns them into rosbags message objects (CDR serialisation without ROS) or into
  rclpy messages;
* :mod:`.mcap_recorder` writes them into an MCAP file (``tactile-deploy run --mcap FILE``) that
  ``ros2 bag play`` and Foxglove read;
* :mod:`.node` is a ROS 2 node (rclpy) publishing the same messages live.
"""
