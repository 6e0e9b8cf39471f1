"""The simulator of the closed loop: scenarios (the paper's and ours), simulate() stepping the
plant, sensors, LQR and estimator over a batch of Monte-Carlo runs (in Python or compiled),
and the results and their statistics. The ROS pipeline equals it in lockstep. May import the
foundation, gains, measurements, spiking, filters and plant; never runners or a ROS package."""
