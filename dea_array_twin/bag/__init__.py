"""ROS 2 bags as MCAP files: writing them as rosbag2 does, reading, recovering, time series.

Holds the ROS 2-profile writer (:mod:`.writer`) with the message definitions and type
hashes it stores (:mod:`.msg_definitions`), the reader of single files and rosbag2
folders (:mod:`.reader`), the twin's config as a bag records it (:mod:`.twin_config`),
recovery of killed recordings (:mod:`.recover`), the choice of command and output
topics (:mod:`.topics`) and their time series (:mod:`.series`).  It may import the
model and the config file reader, and the optional ``mcap`` packages; never rclpy
(message bytes come in and go out already serialised), so bags can be read and
written without a ROS installation.
"""
