"""ROS 2 bags in and out (the `ros` extra: rosbags, mcap).

In: a rosbag2 recording (its folder, or its .mcap / .db3 file; a ROS 1 .bag too) becomes a sequence of native scans
(rafd.scans.native's layout: per-azimuth times and encoder angles in the header columns) that the service's native
path reads, with the range bin the bag's configuration gives (rafd.ros.reader, rafd.ros.scans); rafd.ros.sequence
makes it a RadarSequence, so every command that reads a sequence reads a bag.

Out: per answered scan, vision_msgs/Detection3DArray, radar_msgs/RadarTracks, nav_msgs/Odometry and tf, in REP-103
axes (rafd.ros.axes: the one conversion from the service's axes), written to a rosbag2 bag that is complete or absent
(rafd.ros.writer).

The message definitions that rosbags does not carry ship in rafd/ros/messages/ with their licences (rafd.ros.types).
Importing this package imports nothing heavy; rosbags is imported by the modules that need it.
"""
