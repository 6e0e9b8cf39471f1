"""ROS 2 layer of snn_rendezvous: the plant, sensor, controller, estimator and recorder nodes,
message conversions, the demo orchestrator and the bag report. The math lives in snn_estimator."""
