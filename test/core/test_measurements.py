"""Measurement models (snn_estimator.measurements) and the sensor (snn_estimator.plant.sensors.MeasurementSensor):
Jacobians against finite differences, h against an independent construction, angle wrapping,
validity, the position model equal to PositionSensor, clear errors."""

import ast
import math
from pathlib import Path

import numpy as np
import pytest

from snn_estimator import ClohessyWiltshire
from snn_estimator.measurements import (
    MODELS,
    NON_FINITE,
    OUT_OF_VIEW,
    REASONS,
    SINGULAR,
    TOO_CLOSE,
    TOO_FAR,
    VALID,
    RelativeGeometry,
    make_model,
    rotation_from_quaternion,
)
from snn_estimator.measurements.position import RelativeGPS
from snn_estimator.plant.sensors import MeasurementSensor, PositionSensor, SamplePeriod

#: The models that see the line of sight (observer, mounting); position and relative_gps measure C x.
GEOMETRIC = [name for name, cls in MODELS.items() if issubclass(cls, RelativeGeometry)]
CARTESIAN = ('position', 'relative_gps')
ANGLE_MODELS = ('range_azimuth_elevation', 'line_of_sight', 'docking_camera')
NOISE = {'position': 1e-2, 'relative_gps': 1e-2, 'range_azimuth_elevation': [1e-4, 1e-6, 1e-6],
         'line_of_sight': [1e-6, 1e-6],
         'range': 1e-4, 'range_rate': 1e-6, 'docking_camera': [2.5e-5, 1e-6, 1e-6]}


def random_quaternion(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def mountings(rng):
    """Identity, and a random rotation with an offset, for both observers."""
    yield {'observer': 'chaser'}
    yield {'observer': 'target'}
    for observer in ('chaser', 'target'):
        yield {'observer': observer, 'mounting_offset': rng.normal(size=3),
               'mounting_rotation': random_quaternion(rng)}


def central_differences(model, x, steps):
    """dh/dx by central differences (through the wrapped residual: a difference across the
    +-pi cut is still small), one column per state, step per state and column."""
    columns = []
    for i in range(x.shape[-1]):
        dx = np.zeros_like(x)
        dx[..., i] = steps[..., i]
        columns.append(model.residual(model.h(x + dx), model.h(x - dx)) / (2.0 * steps[..., i:i + 1]))
    return np.stack(columns, axis=-1)


def fd_steps(model, x):
    """Steps well below the distance to the nearest singularity (the range; for angles the
    distance of the line of sight from the sensor z axis)."""
    if model.name in CARTESIAN:
        return np.full(x.shape, 1e-3)
    rho = model.line_of_sight(x)
    scale = np.hypot(rho[..., 0], rho[..., 1]) if model.name in ANGLE_MODELS else np.linalg.norm(rho, axis=-1)
    steps = np.empty(x.shape)
    steps[..., :3] = 1e-5 * scale[..., None]
    steps[..., 3:] = 1e-5 * (1.0 + np.abs(x[..., 3:]))
    return steps


def check_jacobian(model, x):
    valid = model.valid(x)
    assert valid.all(), [REASONS[c] for c in model.validity(x)]
    analytic = model.jacobian(x)
    numeric = central_differences(model, x, fd_steps(model, x))
    scale = np.abs(analytic).max(axis=(-2, -1), keepdims=True)
    assert np.all(np.abs(analytic - numeric) <= 1e-6 * scale), np.abs(analytic - numeric).max()


@pytest.mark.parametrize('name', list(MODELS))
def test_every_jacobian_equals_central_differences_at_random_states(name):
    rng = np.random.default_rng(list(MODELS).index(name))
    for mounting in (mountings(rng) if name in GEOMETRIC else [{}]):
        model = make_model(name, NOISE[name], **mounting)
        x = np.concatenate([rng.normal(size=(200, 3)) * rng.choice([0.5, 50.0, 5000.0], size=(200, 1)),
                            rng.normal(size=(200, 3))], axis=1)
        keep = model.valid(x)
        assert keep.mean() > 0.95  # no field of view: only singular samples drop out
        check_jacobian(model, x[keep])


@pytest.mark.parametrize('name', ANGLE_MODELS)
@pytest.mark.parametrize('distance', [1e-2, 1e-4, 1e-6])
def test_angle_jacobians_stay_exact_close_to_the_sensor_z_axis(name, distance):
    """Near the azimuth singularity (line of sight almost along the sensor z axis) H grows as
    1/distance; the analytic H still matches finite differences taken at a smaller scale."""
    rng = np.random.default_rng(7)
    model = make_model(name, NOISE[name], observer='target')
    phi = rng.uniform(-math.pi, math.pi, size=50)
    r = rng.uniform(1.0, 100.0, size=50)
    sign = rng.choice([-1.0, 1.0], size=50)
    p = np.stack([distance * r * np.cos(phi), distance * r * np.sin(phi), sign * r], axis=1)
    x = np.concatenate([p, rng.normal(size=(50, 3))], axis=1)
    check_jacobian(model, x)


@pytest.mark.parametrize('name', GEOMETRIC)
def test_range_jacobians_stay_exact_at_short_range(name):
    rng = np.random.default_rng(3)
    model = make_model(name, NOISE[name])
    p = rng.normal(size=(50, 3))
    p *= (1e-3 / np.linalg.norm(p, axis=1))[:, None]  # 1 mm
    check_jacobian(model, np.concatenate([p, rng.normal(size=(50, 3)) * 1e-3], axis=1))


@pytest.mark.parametrize('name', ANGLE_MODELS)
def test_on_the_sensor_z_axis_the_angles_are_singular_and_not_measured(name):
    model = make_model(name, NOISE[name], observer='target')
    x = np.array([[0.0, 0.0, 10.0, 1.0, 0.0, 0.0], [0.0, 0.0, -3.0, 0.0, 0.0, 0.0],
                  [1e-11, 0.0, 50.0, 0.0, 0.0, 0.0]])
    assert model.validity(x).tolist() == [SINGULAR] * 3
    assert np.isnan(model.jacobian(x[:2])).any(axis=(1, 2)).all()
    sensor = MeasurementSensor(model, seeds=[0, 1, 2])
    sample = sensor.measure(x)
    assert not sample.valid.any() and np.isnan(sample.z).all() and sample.counts() == {'singular': 3}


@pytest.mark.parametrize('name', GEOMETRIC)
def test_at_range_zero_nothing_is_measured(name):
    model = make_model(name, NOISE[name])
    x = np.array([[0.0, 0.0, 0.0, 1.0, 2.0, 3.0]])
    assert model.validity(x).tolist() == [TOO_CLOSE]
    sample = MeasurementSensor(model).measure(x)
    assert np.isnan(sample.z).all() and sample.counts() == {'too_close': 1}


def test_h_inverts_an_independent_spherical_construction():
    """Build the state from chosen (r, az, el) through the documented conventions (rho in
    sensor axes -> LVLH through the mounting -> chaser position) and read them back."""
    rng = np.random.default_rng(11)
    for observer, sign in (('chaser', -1.0), ('target', 1.0)):
        q, d = random_quaternion(rng), rng.normal(size=3)
        model = make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation'], observer=observer,
                           mounting_offset=d, mounting_rotation=q)
        los_model = make_model('line_of_sight', NOISE['line_of_sight'], observer=observer,
                               mounting_offset=d, mounting_rotation=q)
        r = rng.uniform(0.5, 5000.0, 100)
        az = rng.uniform(-math.pi, math.pi, 100)
        el = rng.uniform(-1.5, 1.5, 100)
        rho = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
        los_lvlh = rho @ rotation_from_quaternion(q).T  # sensor -> LVLH components
        p = sign * (los_lvlh + d)
        x = np.concatenate([p, np.zeros((100, 3))], axis=1)
        np.testing.assert_allclose(model.h(x), np.stack([r, az, el], axis=1), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(los_model.h(x), np.stack([az, el], axis=1), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize('name', list(MODELS))
def test_position_of_inverts_h_where_one_sample_determines_the_position(name):
    """h(position_of(z)) = z for any mounting and observer (range and both angles, position on
    every axis); None where one sample does not fix the position (a restart cannot use it)."""
    rng = np.random.default_rng(11)
    for geometry in (mountings(rng) if name in GEOMETRIC else [{}]):
        model = make_model(name, NOISE[name], **geometry)
        x = np.concatenate([rng.uniform(-80.0, 80.0, size=(20, 3)), rng.normal(size=(20, 3))], axis=1)
        x = x[model.valid(x)]
        p = model.position_of(model.h(x))
        if name in (*CARTESIAN, 'range_azimuth_elevation', 'docking_camera'):
            np.testing.assert_allclose(p, x[:, :3], rtol=0, atol=1e-9)
        else:
            assert p is None
    assert make_model('position', 1e-2, measured_axes=(0, 2)).position_of(np.zeros(2)) is None


def test_angle_conventions_in_the_lvlh_frame():
    """Identity mounting, sensor on the target: azimuth from +x (V-bar) toward +y (-H-bar),
    elevation positive toward +z (R-bar, toward Earth); on the chaser the target is seen at -p."""
    target = make_model('line_of_sight', NOISE['line_of_sight'], observer='target')
    chaser = make_model('line_of_sight', NOISE['line_of_sight'], observer='chaser')
    deg = math.radians
    x = np.array([[10.0, 0.0, 0.0, 0, 0, 0], [0.0, 10.0, 0.0, 0, 0, 0], [10.0, 0.0, 10.0, 0, 0, 0]])
    np.testing.assert_allclose(target.h(x), [[0, 0], [deg(90), 0], [0, deg(45)]], atol=1e-15)
    # the chaser 100 m behind on V-bar (x = -100) sees the target straight along its +x axis
    np.testing.assert_allclose(chaser.h(np.array([-100.0, 0, 0, 0, 0, 0])), [0.0, 0.0], atol=1e-15)
    flipped = make_model('line_of_sight', NOISE['line_of_sight'], observer='target',
                         mounting_rotation=[1.0, 0.0, 0.0, 0.0])  # 180 deg about x: +z away from Earth
    np.testing.assert_allclose(flipped.h(x[2]), [0.0, deg(-45)], atol=1e-15)


def test_range_rate_is_the_time_derivative_of_the_range():
    rng = np.random.default_rng(5)
    for observer in ('chaser', 'target'):
        d = rng.normal(size=3)
        rng_model = make_model('range', 1e-4, observer=observer, mounting_offset=d)
        rate_model = make_model('range_rate', 1e-6, observer=observer, mounting_offset=d)
        x = np.concatenate([rng.normal(size=(100, 3)) * 50, rng.normal(size=(100, 3))], axis=1)
        dt = 1e-4
        ahead, behind = x.copy(), x.copy()
        ahead[:, :3] += x[:, 3:] * dt
        behind[:, :3] -= x[:, 3:] * dt
        numeric = (rng_model.h(ahead) - rng_model.h(behind)) / (2 * dt)
        np.testing.assert_allclose(rate_model.h(x), numeric, rtol=1e-6, atol=1e-9)


def test_angle_residuals_wrap_at_pi():
    model = make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation'])
    deg = math.radians
    z, predicted = np.array([10.0, deg(179), deg(1)]), np.array([10.5, deg(-179), deg(-1)])
    np.testing.assert_allclose(model.residual(z, predicted), [-0.5, deg(-2), deg(2)], atol=1e-12)
    np.testing.assert_allclose(model.residual(predicted, z), [0.5, deg(2), deg(-2)], atol=1e-12)
    los = make_model('line_of_sight', NOISE['line_of_sight'])
    batch = los.residual(np.array([[deg(-179), 0.0], [deg(90), 0.0]]), np.array([[deg(179), 0.0], [deg(-90), 0.0]]))
    np.testing.assert_allclose(batch, [[deg(2), 0.0], [-math.pi, 0.0]], atol=1e-12)
    # a range-only model does not wrap
    assert make_model('range', 1e-4).residual(np.array([10.0]), np.array([0.0])).tolist() == [10.0]


def test_measured_azimuth_behind_the_sensor_stays_within_minus_pi_and_pi():
    model = make_model('line_of_sight', [1e-2, 1e-6], observer='target')
    x = np.tile([-10.0, 0.0, 0.0, 0, 0, 0], (500, 1))  # straight behind the boresight: azimuth pi
    z = MeasurementSensor(model, seeds=range(500)).measure(x).z
    assert np.all((z[:, 0] >= -math.pi) & (z[:, 0] < math.pi))
    assert (z[:, 0] > 0).any() and (z[:, 0] < 0).any()  # both sides of the cut
    assert np.all(np.abs(model.residual(z, model.h(x))[:, 0]) < 0.5)


def test_field_of_view_and_range_limits_decide_what_is_measured():
    model = make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation'], observer='target',
                       field_of_view=math.radians(40.0), min_range=1.0, max_range=300.0)
    x = np.array([[100.0, 0.0, 0.0, 0, 0, 0],                       # on the boresight
                  [100.0, 100 * math.tan(math.radians(19.0)), 0, 0, 0, 0],   # 19 deg off: inside
                  [100.0, 100 * math.tan(math.radians(21.0)), 0, 0, 0, 0],   # 21 deg off: outside
                  [-100.0, 0.0, 0.0, 0, 0, 0],                      # behind
                  [400.0, 0.0, 0.0, 0, 0, 0],                       # too far
                  [0.5, 0.0, 0.0, 0, 0, 0],                         # too close
                  [0.0, 0.0, 0.0, 0, 0, 0]])                        # range 0
    expected = [VALID, VALID, OUT_OF_VIEW, OUT_OF_VIEW, TOO_FAR, TOO_CLOSE, TOO_CLOSE]
    assert model.validity(x).tolist() == expected
    sample = MeasurementSensor(model, seeds=range(7)).measure(x)
    assert sample.valid.tolist() == [c == VALID for c in expected]
    assert np.isfinite(sample.z[:2]).all() and np.isnan(sample.z[2:]).all()
    assert sample.counts() == {'out_of_view': 2, 'too_far': 1, 'too_close': 2}


def test_a_noisy_range_outside_the_limits_is_discarded():
    model = make_model('range', 1.0, observer='target', min_range=1.0, max_range=10.0)
    x = np.tile([1.05, 0.0, 0.0, 0, 0, 0], (400, 1))  # valid truth, but sigma 1 m around 1.05 m
    sample = MeasurementSensor(model, seeds=range(400)).measure(x)
    assert np.all(sample.z[sample.valid] >= 1.0) and 100 < (~sample.valid).sum() < 300
    assert set(sample.counts()) == {'too_close'}


@pytest.mark.parametrize('axes', [(0, 1, 2), (0, 2), (1,)])
def test_position_model_draws_positionsensors_numbers_with_the_same_seed(axes):
    seeds = [3, 4, 5]
    m = len(axes)
    a = np.random.default_rng(m).normal(size=(m, m)) * 0.1
    noise = a @ a.T + 1e-3 * np.eye(m)  # a full R: its square root is not symmetric
    old = PositionSensor(ClohessyWiltshire(measured_axes=axes), noise, seeds)
    new = MeasurementSensor(make_model('position', noise, measured_axes=axes), seeds)
    rng = np.random.default_rng(0)
    for _ in range(600):  # beyond the 512-row block of the noise stream
        x = rng.normal(size=(3, 6)) * 100
        sample = new.measure(x)
        assert sample.valid.all()
        np.testing.assert_allclose(sample.z, old.measure(x), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(new.model.jacobian(x)[0], ClohessyWiltshire(measured_axes=axes).measurement_matrix)


def test_dropouts_remove_about_their_share_and_do_not_shift_the_noise():
    model = make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation'], observer='target')
    seeds = list(range(20))
    lossy, clean = MeasurementSensor(model, seeds, dropout_probability=0.3), MeasurementSensor(model, seeds)
    x = np.tile([50.0, 5.0, -3.0, 0, 0, 0], (20, 1))
    dropped = 0
    for _ in range(100):
        a, b = lossy.measure(x), clean.measure(x)
        assert b.valid.all()
        np.testing.assert_array_equal(a.z[a.valid], b.z[a.valid])
        dropped += (~a.valid).sum()
    assert 0.25 < dropped / 2000 < 0.35
    with pytest.raises(ValueError, match='dropout_probability'):
        MeasurementSensor(model, seeds, dropout_probability=1.5)


@pytest.mark.parametrize('name, noise, message', [
    ('range_azimuth_elevation', [1.0, 2.0], r'R of range_azimuth_elevation, 3x3 in m\^2, rad\^2, rad\^2'),
    ('line_of_sight', np.eye(3), r'R of line_of_sight, 2x2'),
    ('range', [1.0, 1.0], r'R of range, 1x1 in m\^2'),
    ('range_rate', [-1.0], 'positive definite'),
    ('position', [[1.0, 2.0], [0.0, 1.0]], 'symmetric'),
])
def test_a_wrong_noise_matrix_is_refused_naming_the_model_and_its_units(name, noise, message):
    kwargs = {'measured_axes': (0, 2)} if name == 'position' else {}
    with pytest.raises(ValueError, match=message):
        make_model(name, noise, **kwargs)


@pytest.mark.parametrize('name', list(MODELS))
def test_every_model_refuses_a_noise_of_the_wrong_size(name):
    model = make_model(name, NOISE[name])
    m = model.dim
    with pytest.raises(ValueError, match=rf'R of {name}, {m}x{m} in'):
        make_model(name, np.ones(m + 1))
    with pytest.raises(ValueError, match='positive definite'):
        make_model(name, np.zeros(m))


@pytest.mark.parametrize('changes, message', [
    ({'mounting_rotation': [0.0, 0.0, 0.0, 2.0]}, 'unit quaternion'),
    ({'mounting_rotation': [0.0, 0.0, 1.0]}, 'mounting_rotation'),
    ({'field_of_view': 0.0}, 'field_of_view'),
    ({'field_of_view': 7.0}, 'at most 2 pi'),
    ({'min_range': 10.0, 'max_range': 5.0}, 'must exceed min_range'),
    ({'observer': 'ground'}, 'observer must be one of chaser, target'),
    ({'mounting_offset': [1.0, 2.0]}, 'mounting_offset'),
])
def test_bad_geometry_parameters_are_refused_with_the_field_named(changes, message):
    with pytest.raises(ValueError, match=message):
        make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation'], **changes)


def test_the_registry_lists_every_model_and_refuses_an_unknown_one():
    assert set(MODELS) == {'position', 'range_azimuth_elevation', 'line_of_sight', 'range', 'range_rate',
                           'docking_camera', 'relative_gps'}
    for name, cls in MODELS.items():
        model = make_model(name, NOISE[name])
        assert model.name == name and isinstance(model, cls)
        assert model.dim == len(model.units) == model.noise.shape[0]
        assert model.message_form in ('point', 'range', 'vector')
    with pytest.raises(ValueError, match='model must be one of position, range_azimuth_elevation'):
        make_model('sonar', 1.0)


def test_the_measurements_package_imports_numpy_and_validation_only():
    root = Path(__file__).resolve().parents[2] / 'snn_estimator' / 'measurements'
    found = set()
    for path in root.glob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                found.add('.' * node.level + (node.module or ''))
    outside = {name for name in found if not name.startswith('.') or name.startswith('..')}
    assert outside <= {'__future__', 'abc', 'math', 'typing', 'numpy', 'snn_estimator.validation'}, outside


def test_the_measurement_bench_times_every_model(tmp_path):
    from snn_tools.bench import measurement as measurement_bench
    out = tmp_path / 'bench.json'
    assert measurement_bench.main(['--repeat', '2', '--runs', '3', '--steps', '25', '--out', str(out)]) == 0
    import json
    figures = json.loads(out.read_text())
    steps = figures.pop('filter_step_us')
    assert set(figures) == {'runs=1', 'runs=3'} == set(steps)
    for rows in figures.values():
        assert set(rows) == {'PositionSensor.measure', *MODELS}
        assert all(value > 0 for name in MODELS for value in rows[name].values())
    for rows in steps.values():  # the filter's step with each model, and on the model's own C
        assert set(rows) == {'model_c', *MODELS}
        assert all(value > 0 for row in rows.values() for value in row.values())


def test_sample_period_keeps_its_grid_whatever_the_truth_steps():
    ms = 1_000_000
    period = SamplePeriod(0.25)
    assert [t for t in range(100, 1101, 100) if period.due(t * ms)] == [100, 400, 600, 900, 1100]
    period.reset()
    assert period.due(50 * ms) and not period.due(250 * ms) and period.due(300 * ms)
    every = SamplePeriod(0.0)
    assert all(every.due(t) for t in (5, 5, 7))
    with pytest.raises(ValueError, match='measurement_period'):
        SamplePeriod(-1.0)


def test_every_model_is_in_the_sensor_tables_of_the_docs():
    root = Path(__file__).resolve().parents[2]
    for document in ('docs/sensors.md', 'README.md'):
        text = (root / document).read_text()
        missing = [name for name in MODELS if f'| `{name}`' not in text]
        assert not missing, f'{document} has no table row for {missing}'


def test_docking_camera_range_noise_grows_as_range_squared_and_its_angles_do_not():
    """sigma_r = sqrt(sigma_r0^2 + (r^2 sigma_px / (f b))^2), sigma_theta constant (the pinhole
    law, docking_camera.py), written out here from f = 1911 px, sigma_px = 0.2 px, b = 0.5 m;
    and the sensor's samples spread by it."""
    floor, angle = 0.005, 1e-3
    model = make_model('docking_camera', [floor ** 2, angle ** 2, angle ** 2],
                       mounting_rotation=[0.0, 0.0, 1.0, 0.0])  # looks back along -x, as in the suites
    ranges = np.array([0.5, 3.0, 10.0, 20.0, 30.0])
    x = np.zeros((len(ranges), 6))
    x[:, 0] = ranges  # the chaser ahead of the target on V-bar
    law = np.sqrt(floor ** 2 + (ranges ** 2 * 0.2 / (1911.0 * 0.5)) ** 2)
    noise = model.noise_at(x)
    np.testing.assert_allclose(np.sqrt(noise[:, 0, 0]), law, rtol=1e-12)
    np.testing.assert_allclose(np.sqrt(noise[:, 0, 0])[[2, 4]], [0.0215, 0.188], rtol=0.01)  # 2.2 cm, 19 cm
    np.testing.assert_allclose(noise[:, 1:, 1:], np.broadcast_to(angle ** 2 * np.eye(2), (5, 2, 2)))
    assert np.all(noise[:, 0, 1:] == 0.0)
    runs = 4000
    for r, sigma in zip(ranges[[1, 3]], law[[1, 3]]):
        truth = np.tile([r, 0.0, 0.0, 0.0, 0.0, 0.0], (runs, 1))
        z = MeasurementSensor(model, seeds=range(runs)).measure(truth).z
        assert abs(np.std(z[:, 0] - r) / sigma - 1.0) < 0.05
        assert abs(np.std(z[:, 1]) / angle - 1.0) < 0.05


def test_a_ranger_without_range_noise_growth_draws_the_same_numbers_as_before():
    """range_noise_growth 0 (every model but docking_camera) keeps R constant and the noise
    draws unchanged; a model that measures no range refuses a growth."""
    x = np.tile([20.0, 1.0, -2.0, 0.0, 0.0, 0.0], (5, 1))
    plain = MeasurementSensor(make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation']), range(5))
    law = make_model('docking_camera', NOISE['range_azimuth_elevation'], range_noise_growth=0.0)
    assert not law.state_dependent_noise
    np.testing.assert_array_equal(plain.measure(x).z, MeasurementSensor(law, range(5)).measure(x).z)
    lidar = make_model('range_azimuth_elevation', NOISE['range_azimuth_elevation'], range_noise_growth=3.3e-4)
    r = np.linalg.norm(x[0, :3])
    assert lidar.noise_at(x)[0, 0, 0] == pytest.approx(1e-4 + (3.3e-4 * r) ** 2, rel=1e-12)
    broken = np.array([[np.inf, 0.0, 0.0, 0.0, 0.0, 0.0], [np.nan, 1.0, 0.0, 0.0, 0.0, 0.0]])
    sample = MeasurementSensor(make_model('docking_camera', NOISE['docking_camera']), range(2)).measure(broken)
    assert sample.counts() == {'non_finite': 2}  # a broken truth is not measured; its draw does not fail
    with pytest.raises(ValueError, match='range_noise_growth: line_of_sight measures no range'):
        make_model('line_of_sight', NOISE['line_of_sight'], range_noise_growth=1e-3)


def test_docking_camera_limits_contact_to_thirty_metres_in_a_thirty_degree_cone():
    """The docking suite's camera (defaults.DOCKING_CAMERA): from a few cm to 30 m, 30 deg full
    field of view about its boresight; nothing closer, farther or outside the cone."""
    from snn_estimator import defaults as D
    camera = D.DOCKING_CAMERA
    model = make_model('docking_camera', camera['noise'], observer='target', field_of_view=camera['field_of_view'],
                       min_range=camera['min_range'], max_range=camera['max_range'])
    assert camera['min_range'] <= 0.05 and camera['max_range'] == 30.0
    assert camera['field_of_view'] == pytest.approx(math.radians(30.0))
    off = math.tan(math.radians(14.0)), math.tan(math.radians(16.0))
    x = np.array([[0.06, 0, 0, 0, 0, 0], [0.04, 0, 0, 0, 0, 0], [29.0, 0, 0, 0, 0, 0], [31.0, 0, 0, 0, 0, 0],
                  [10.0, 10.0 * off[0], 0, 0, 0, 0], [10.0, 0, 10.0 * off[1], 0, 0, 0]])
    assert [REASONS[c] for c in model.validity(x)] == ['valid', 'too_close', 'valid', 'too_far', 'valid',
                                                       'out_of_view']


def test_relative_gps_is_the_position_inside_its_range_limits_and_draws_position_sensor_s_noise():
    """relative_gps (the approach's far sensor, decision 72): h = C x, TOO_CLOSE inside min_range,
    TOO_FAR beyond max_range; its MeasurementSensor's samples equal PositionSensor's where valid."""
    gps = RelativeGPS(1e-2 * np.eye(3), min_range=500.0, max_range=6000.0)
    x = np.array([[-400.0, 3.0, 1.0, 0, 0, 0], [-2000.0, 3.0, 1.0, 0, 0, 0], [-7000.0, 0, 0, 0, 0, 0],
                  [np.nan, 0, 0, 0, 0, 0]])
    np.testing.assert_array_equal(gps.validity(x), [TOO_CLOSE, VALID, TOO_FAR, NON_FINITE])
    np.testing.assert_array_equal(gps.h(x[:3]), x[:3, :3])
    seeds = [0, 1, 2]
    sample = MeasurementSensor(gps, seeds).measure(x[:3])
    reference = PositionSensor(ClohessyWiltshire(), 1e-2 * np.eye(3), seeds).measure(x[:3])
    np.testing.assert_array_equal(sample.z[1], reference[1])
    assert np.isnan(sample.z[[0, 2]]).all()
    with pytest.raises(ValueError, match='min_range < max_range'):
        RelativeGPS(1e-2 * np.eye(3), min_range=500.0, max_range=100.0)
