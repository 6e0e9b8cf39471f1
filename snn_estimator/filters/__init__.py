"""The filters of the paper behind one interface: the Estimator (EKF, EMSIF, SIF and
their spiking networks), its compiled step kernels and the numpy reference forms.
May import the foundation (models, schema, config, catalog), gains, measurements and spiking."""
