"""The offline closed loop: truth (CW, Basilisk), sensors, LQR and the batched Monte-Carlo
simulate() that the ROS pipeline equals in lockstep. May import everything in the core
but loop."""
