"""snn_tools: what runs around the pipeline, never inside a node.

The demo orchestrator, the paper's experiments and Monte-Carlo campaigns, figures and reports,
benchmarks, bag tools and the neuromorphic export. It may import the core (snn_estimator) and
the ROS layer (scenario_nodes); neither of those imports it.
"""
