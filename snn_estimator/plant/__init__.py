"""The blocks of the loop around the estimator: the truth (the CW model or Basilisk), the
sensors that measure it and the LQR that closes the loop. The cw_plant, basilisk_plant,
position_sensor and lqr_controller nodes wrap these (and load no numba); the simulator
(snn_estimator.sim) steps the same objects. May import the foundation and measurements."""
