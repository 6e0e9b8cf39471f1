"""Running in a real loop, without ROS: the FilterRunner and the plant runner the nodes wrap,
input gates and peer watch. The FilterRunner is composed of parts that own their state: the
measurement queue (gating), the control book, the start-up strategy (least-squares starts), the
provisional-step log, the restart trigger and recovery, and the report. May import the foundation,
filters and plant; never sim, never a ROS package."""
