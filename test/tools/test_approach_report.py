"""The reading of results/REPORT.md's approach section (snn_tools.experiments.approach): the
models' drift over a dwell, with and without the J2 model's row (results files written before
ss_j2 existed keep their reading)."""

from snn_tools.experiments.approach import drift_reading

ROW = {'distance': 5000.0, 'dwell': 300.0, 'cw_vs_nonlinear': 0.324, 'nonlinear_vs_two_body': 2.4e-9,
       'nonlinear_vs_two_body_j2': 0.906}


def test_the_drift_reading_names_the_j2_models_figure_when_the_rows_hold_it():
    text = drift_reading([{**ROW, 'cw_vs_two_body_j2': 0.872, 'ss_j2_vs_two_body_j2': 0.872}])
    assert 'the Schweighart-Sedwick J2 model (ss_j2) from two-body with J2 0.872 m' in text
    assert 'from two-body with J2 0.906 m' in text and 'orbit average' in text and 'decisions.md, 82' in text


def test_rows_without_the_j2_model_keep_the_reading_they_had():
    text = drift_reading([ROW])
    assert 'ss_j2' not in text and 'J2, which neither model holds, is the larger model error' in text
    assert text.startswith("Why the nonlinear model gains little here: over one hold's dwell")
