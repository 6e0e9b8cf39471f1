"""Speed: the filter steps, the closed loop over ROS (throughput and latency), campaigns, the live
view, codecs, measurement models."""
