"""Running in a real loop, without ROS: the FilterRunner and the plant runner the nodes wrap,
input gates, recovery, least-squares starts and peer watch. May import the foundation
and filters; never offline, never a ROS package."""
