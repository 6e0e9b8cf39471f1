"""Running in a real loop, without ROS: the FilterRunner and the plant runner the nodes wrap,
input gates, recovery, least-squares starts and peer watch. May import the foundation,
filters and plant; never sim, never a ROS package."""
