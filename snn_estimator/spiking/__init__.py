"""The spiking networks: their state and weights (Eq. 10-22), the fixed-point chip network,
the spiking LQR and the cost of a step. May import the foundation and gains;
filters only inside functions (the chip steps beside the Estimator)."""
