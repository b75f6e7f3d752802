"""ROS 2 wire formats: CDR encoding of optitac_msgs, and rmw_zenoh's names for them on Zenoh.

Pure functions and small classes with no I/O; :mod:`optitac_edge.io.publishers`
puts the bytes on the network. The message definitions (``msg/*.msg``) are
package data, shared with the ROS 2 package ``ros2/optitac_msgs``.
"""
