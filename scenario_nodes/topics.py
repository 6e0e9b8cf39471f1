"""Topic names of the pipeline, defined once and free of rclpy (bag_tools reads bags without
ROS); scenario_nodes.qos re-exports them beside the QoS profiles.

Relative names, so namespaces and remapping work.
"""

TRUTH = 'truth'
MEASUREMENT = 'measurement'
CONTROL = 'control'
#: plant output: the control it stepped with over [t_k, t_k+1] (geometry_msgs/AccelStamped, stamp
#: t_k): the controller's u_k, or the one in force when u_k came late or never (zero once expired)
APPLIED_CONTROL = 'applied_control'
ESTIMATE = 'estimate'
SPIKE_COUNT = 'spike_count'
SPIKES = 'spikes'
DIAGNOSTICS = 'diagnostics'
SET_STATE = 'set_state'  # estimator input: replace the estimate (nav_msgs/Odometry)
CLOCK = '/clock'
#: lqr_controller output with guidance approach: one diagnostic_msgs/DiagnosticArray per guidance
#: event (arrive, go, no-go, abort), stamped at its time; the plant may end the run on it
GUIDANCE = 'guidance'

PIPELINE_TOPICS = (TRUTH, MEASUREMENT, CONTROL, ESTIMATE, SPIKE_COUNT, SPIKES, DIAGNOSTICS)
MARKERS = 'markers'  # live_view output: visualization_msgs/MarkerArray of the scene (RViz)
