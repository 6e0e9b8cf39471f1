"""The numbers of the scenarios, written once: the paper's values (Table 6, Sec. 3.2; Table 1,
Sec. 3.1) and this package's choices where the paper is silent (docs/decisions.md).

The core's configuration and scenarios, the ROS parameter tables (and from them the YAML files
in config/ and docs/parameters.md) all take their defaults from here.
"""

#: Earth's gravitational parameter, m^3/s^2 (Table 6 gives 398600 km^3/s^2).
EARTH_MU = 3.986e14
#: Target orbit radius, m: a 400 km circular LEO (not stated in the paper; Decision 5).
ORBIT_RADIUS = 6_778_137.0
#: Target orbit inclination, rad: the ISS's 51.6 deg (Basilisk's OrbitSettings and the J2 model's default).
ORBIT_INCLINATION = 0.9005898940290741  # math.radians(51.6)
#: Earth's unnormalised J2 and the equatorial radius it refers to, m (Basilisk's truth and the
#: Schweighart-Sedwick model use the same numbers).
EARTH_J2 = 1.08262668e-3
EARTH_EQUATORIAL_RADIUS = 6_378_137.0

# ---------------------------------------------------------------- rendezvous (Sec. 3.2, Table 6)
#: x0 = [r0, v0]: m and m/s in the target's LVLH frame.
RENDEZVOUS_X0 = (70.0, 30.0, -5.0, -1.7, -0.9, 0.25)
#: Sample period and duration, s.
RENDEZVOUS_TIME_STEP = 0.1
RENDEZVOUS_DURATION = 360.0
#: Q, process-noise spectral density of the truth, (m/s^2)^2/Hz (Table 6: 1e-12 I6).
RENDEZVOUS_PROCESS_NOISE = 1e-12
#: R, position-noise variance per sample, m^2 (Table 6: 1e-2 I3).
RENDEZVOUS_MEASUREMENT_NOISE = 1e-2
#: The filters' Q_hat = 0.9 Q and R_hat = 5 R (Sec. 3.2).
RENDEZVOUS_PROCESS_NOISE_SCALE = 0.9
RENDEZVOUS_MEASUREMENT_NOISE_SCALE = 5.0
#: Network (Table 6): N, lambda (1/s), delta (m), decoder variance (Sec. 3.2: 1/15).
RENDEZVOUS_NEURONS = 200
RENDEZVOUS_LEAK_RATE = 0.001
RENDEZVOUS_BOUNDARY_LAYER = 0.1
RENDEZVOUS_DECODER_VARIANCE = 1.0 / 15.0
#: spike_rule synchronous (Decisions 58-59; results/neuromorphic.md, make spike-rules): T = 100
#: chip ticks per 0.1 s sample (1 ms), thresholds widened by w = 2 (3 ||D_i||^2 / 2: the one
#: setting measured within 1.2x the twin's RMSE and 2x greedy's spikes on position and LIDAR for
#: both kinds; w = 1 spends 2.2-2.3x greedy's spikes on position), no refractory ticks, K = 10
#: firing slots (neuron i fires only when (t + i) mod 10 = 0).
SYNCHRONOUS_TICKS = 100
SYNCHRONOUS_WIDENING = 2.0
SYNCHRONOUS_REFRACTORY = 0
SYNCHRONOUS_SLOTS = 10
#: P0 (not stated; Decision 6): one sensor sigma in position, 1 cm/s in velocity.
RENDEZVOUS_INITIAL_COVARIANCE = (1e-2, 1e-2, 1e-2, 1e-4, 1e-4, 1e-4)
#: Network state scaling S (Decision 10): 1 cm and 0.1 mm/s per unit.
RENDEZVOUS_STATE_SCALE = (1e-2, 1e-2, 1e-2, 1e-4, 1e-4, 1e-4)
#: LQR weights Qc, Rc (not stated; Decision 7).
LQR_STATE_WEIGHT = 1.0
LQR_INPUT_WEIGHT = 1e5
#: Window of the tables' RMSE (Table 7: the last 60 s).
RENDEZVOUS_METRIC_WINDOW = 60.0
#: Seconds of measurements a joining estimator fits its least-squares start to: 10 s leaves
#: ~2 cm in position and ~3.5 mm/s in velocity (1 sigma) at R = 1e-2 m^2 per 0.1 s sample.
INITIAL_FIT_WINDOW = 10.0

# ---------------------------------------------------------------- Van der Pol (Sec. 3.1, Table 1)
VAN_DER_POL_MU = 0.005
VAN_DER_POL_X0 = (2.0, 2.0)
VAN_DER_POL_TIME_STEP = 0.01
VAN_DER_POL_DURATION = 20.0

# ---------------------------------------------------------------- the approach's observability hop
#: The angles suite's out-of-plane hop (docs/decisions.md, 74): at the 5 km hold, 200 m out of
#: plane, 300 s after arrival (snn_estimator.sim.approach.ANGLES_HOP; the controller node's
#: observability_hold, observability_hop_size, observability_hop_delay).
ANGLES_HOP_HOLD, ANGLES_HOP_SIZE, ANGLES_HOP_DELAY = '5 km', 200.0, 300.0

# ---------------------------------------------------------------- far range (not in the paper)
#: V-bar approach from 5 km behind the target to a hold point 100 m behind it, ~1 orbit.
FAR_RANGE_X0 = (-5000.0, 0.0, 0.0, 0.0, 0.0, 0.0)
FAR_RANGE_SETPOINT = (-100.0, 0.0, 0.0, 0.0, 0.0, 0.0)
FAR_RANGE_TIME_STEP = 1.0
FAR_RANGE_DURATION = 5600.0
FAR_RANGE_METRIC_WINDOW = 600.0
#: LQR weights: reach the hold point in about an orbit with commands far below the thrust limit.
FAR_RANGE_LQR_STATE_WEIGHT = 1.0
FAR_RANGE_LQR_INPUT_WEIGHT = 1e10
#: The filters start from a dispersed estimate with P0 of 0.2 m and 1 cm/s (an Euler step of
#: Eq. 6 at 1 s allows P0 up to R = 0.05 m^2 on the measured axes); the network's scale 10 cm and
#: 1 mm/s per unit (5 km of positions in 5e4 units).
FAR_RANGE_ESTIMATOR = {
    'initial_state': FAR_RANGE_X0, 'initial_covariance': (0.04, 0.04, 0.04, 1e-4, 1e-4, 1e-4),
    'initial_state_dispersion': True, 'state_scale': (0.1, 0.1, 0.1, 1e-3, 1e-3, 1e-3)}

# ---------------------------------------------------------------- sensor models (issue 22; not in the paper)
#: R per sample of each sensor model in its units: LIDAR range 0.1 m (Table 6's position sigma)
#: and angles 1 mrad; camera angles 1 mrad.
SENSOR_NOISE = {'position': RENDEZVOUS_MEASUREMENT_NOISE, 'range_azimuth_elevation': (1e-2, 1e-6, 1e-6),
                'line_of_sight': (1e-6, 1e-6), 'range': 1e-2, 'range_rate': 1e-6,
                'docking_camera': (2.5e-5, 1e-6, 1e-6)}
#: A sensor's boundary layer delta per component from its noise R (Decision 35): Table 6's delta =
#: 0.1 is one sigma of its R = 1e-2 m^2 and also 10 R. 'sigma': delta_j = sqrt(R_jj) (the
#: default: 0.1 m for a range, 1e-3 rad for a 1 mrad angle); 'variance': delta_j = 10 R_jj, in
#: the units of the diag(P^zz) Eq. 8 divides by it (1e-5 rad^2 for the angle).
BOUNDARY_LAYER_UNITS = ('sigma', 'variance')
SENSOR_BOUNDARY_LAYER_UNITS = 'sigma'
SENSOR_BOUNDARY_LAYER_PER_VARIANCE = RENDEZVOUS_BOUNDARY_LAYER / RENDEZVOUS_MEASUREMENT_NOISE
#: The spiking networks on the close-approach sensors (Decision 36): the deviation coding (13b) in
#: units of 1 mm and 0.01 mm/s, a tenth of Table 6's network (RENDEZVOUS_STATE_SCALE). A LIDAR's
#: angles leave the EKF ~1 mm and ~2e-5 m/s off where the sensor falls silent; the paper's coding
#: in 1 cm and 0.1 mm/s units codes the state ~0.3 units (3e-5 m/s) off, which 240 s of dead
#: reckoning turn into centimetres.
SENSOR_NETWORK = {'network_coding': 'deviation', 'state_scale': (1e-3, 1e-3, 1e-3, 1e-5, 1e-5, 1e-5)}
#: The close approach's sensor on the chaser, 70 m ahead of the target: boresight LVLH -x
#: (180 deg about z, quaternion [x, y, z, w]), looking back at the target.
CLOSE_SENSOR_MOUNTING = (0.0, 0.0, 1.0, 0.0)
#: Its minimum range, m: closer, no sample (sensor_msgs/Range: discard). An EKF on angles fails
#: once the range is comparable to its position error (h is far from linear over the error) and
#: H grows as 1/range; without a limit the close approach diverges (docs/sensors.md).
CLOSE_SENSOR_MIN_RANGE = 0.3
#: The hand-over (camera far, LIDAR close; not in the paper): the LIDAR's maximum range, m, and
#: the steps between two samples of each sensor (camera 10 Hz, LIDAR 5 Hz at dt = 0.1 s).
HANDOVER_LIDAR_MAX_RANGE = 30.0
HANDOVER_PERIODS = (1, 2)

# ---------------------------------------------------------------- the docking suite (issue 38; not in the paper)
#: Sensors as flown (docs/sensors.md, "The docking suite", gives the source of every value). A
#: rendezvous LIDAR of the Jena-Optronik RVS class (ATV, HTV, Cygnus): 1.8 m (ATV's
#: telegoniometer) to 3000 m, range noise sqrt(0.033^2 + (3.3e-4 r)^2) m (0.1 m 3 sigma close in;
#: 0.1 % of r 3 sigma, the time-of-flight class), angles 0.13 deg (< 0.4 deg 3 sigma), 3 Hz: a
#: sample every 3 steps of 0.1 s. No field-of-view limit: the chaser's attitude (its pointing)
#: is not in the state (Decision 46). R_hat, the filter's R, is the R at ``design_range`` m
#: (Decision 46: the filters take one R per sensor).
DOCKING_LIDAR = {'noise': (1.089e-3, 5.29e-6, 5.29e-6),  # (0.033 m)^2, (2.3e-3 rad)^2
                 'range_noise_growth': 3.3e-4,
                 'min_range': 1.8, 'max_range': 3000.0, 'period_steps': 3, 'design_range': 100.0}
#: A docking camera (videometer, VGS class) on a retro-reflector pattern: range and line of sight
#: (docking_camera.py's pinhole law: sigma_r = sqrt(0.005^2 + (r^2 0.2 / (1911 x 0.5))^2) m,
#: angles 1 mrad), 30 deg full field of view, from 5 cm (a short-range pattern at the docking
#: port) to 30 m, 5 Hz: a sample every 2 steps.
DOCKING_CAMERA = {'noise': (2.5e-5, 1e-6, 1e-6),  # (5 mm)^2, (1 mrad)^2
                  'field_of_view': 0.5235987755982988,
                  'min_range': 0.05, 'max_range': 30.0, 'period_steps': 2, 'design_range': 10.0}
#: Angles-only far approach (open loop): the chaser 1 km behind the target and 50 m below its
#: orbit (z toward Earth) drifts toward it under free CW motion (x' = 1.5 n z); a camera on the
#: chaser looks forward (identity mounting: boresight LVLH +x). 1 s samples over 3000 s.
ANGLES_ONLY_X0 = (-1000.0, 0.0, 50.0, 0.0, 0.0, 0.0)  # vx set to the drift 1.5 n z by the scenario
ANGLES_ONLY_TIME_STEP = 1.0
ANGLES_ONLY_DURATION = 3000.0
ANGLES_ONLY_METRIC_WINDOW = 600.0
#: The estimate starts 30 m off along the line of sight (3 % of the range) and 1 m across it;
#: P0 says so (30 m, 1 m, 1 m, 1 cm/s). A larger P0 along x fails Estimator.check_time_step at
#: 1 s steps: with the chaser 50 m below, the elevation sees x as 50/r^2 rad/m.
ANGLES_ONLY_INITIAL_ERROR = (30.0, 1.0, -1.0, 0.0, 0.0, 0.0)
ANGLES_ONLY_INITIAL_COVARIANCE = (900.0, 1.0, 1.0, 1e-4, 1e-4, 1e-4)
#: The observability maneuver: a known radial burn (m/s^2, LVLH) held over [start, end) s.
ANGLES_ONLY_MANEUVER = (500.0, 520.0, (0.0, 0.0, -2.5e-3))
