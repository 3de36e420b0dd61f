"""The ROS 2 protocol over zenoh, as a library: CDR messages (rosbags' type store), the two key
styles (zenoh-bridge-ros2dds and rmw_zenoh), a node that publishes, subscribes and serves over a
transport port, occupancy grids and the per-robot profiles. Never imports zenoh itself: the transport
is injected (robot-io's ``ros2_zenoh.py`` is the zenoh one). Robot-io's ROS 2 backend and stand-in,
and the deploy tools, are its users."""
