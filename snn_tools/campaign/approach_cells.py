"""The campaign cells of the approach (``scenario: approach``; issue 39, item 4): settings ->
:func:`snn_estimator.sim.approach.approach_scenario` -> ``runs`` flights of one filter
(:func:`fly_approach`) -> :func:`summarize` -> one flat row of the safety figures.

An approach cell is not a Monte-Carlo batch of the generic Scenario (no final window, no RMSE):
its runs end at contact, abort or no-go, and its row is the summary of its flights. So it has its
own check, batch and combine, which snn_tools.campaign.cells dispatches to by scenario name.

The row's columns are summarize()'s names flattened with ``_`` (``outcomes_contact``,
``closing_speed_mean``, ``holds_250m_hold_error_max``; hold names lose their spaces), every
statistic as mean, min, max and n (all None when no run gave the figure), and ``contact_rate``,
contacts over runs. The holds are always the module's four (HOLDS), so cells that start at
another hold (``first_hold``) have the same columns, None where they never held.
"""

from __future__ import annotations

from snn_estimator.sim.approach import (
    HOLDS,
    LEGS,
    ApproachScenario,
    approach_scenario,
    fly_approach,
    summarize,
)

#: The holds an approach may start at (``first_hold``), outermost first.
FIRST_HOLDS = tuple(hold.name for hold in HOLDS)
#: The statistics summarize() gives for a figure (its _stats), in its order.
STATISTICS = ('mean', 'min', 'max', 'n')


def _column(key) -> str:
    """A key of summarize() as a part of a column name (hold names lose their spaces)."""
    return str(key).replace(' ', '')


#: The columns summary.md and campaign.html show (every column is in results.parquet): contacts,
#: the contact conditions, corridor exits, keep-out entries before the go, aborts and no-gos,
#: delta-v (m/s), mean NEES, the hold-point error (m) at each hold's decision (go or no-go), spikes per run.
TABLE_COLUMNS = ('contact_rate', 'success', 'closing_speed_mean', 'closing_speed_max', 'lateral_at_contact_max',
                 'corridor_violation_runs', 'keep_out_entry_before_go', 'outcomes_abort', 'outcomes_no_go',
                 'delta_v_mean', 'nees_mean', *(f'holds_{_column(h.name)}_hold_error_mean' for h in HOLDS),
                 'spikes_mean')


def approach_cell_scenario(first_hold: str = FIRST_HOLDS[0], **changes) -> ApproachScenario:
    """:func:`approach_scenario` started at the hold named ``first_hold`` (the holds and legs
    after it as the module's; the 250 m and 20 m holds make a cell of seconds, not minutes);
    ``changes``: approach_scenario's keywords (dynamics_model, plant, sensors, orbit_radius,
    max_duration) and EstimatorConfig fields."""
    if first_hold not in FIRST_HOLDS:
        raise ValueError(f"first_hold must be one of {', '.join(FIRST_HOLDS)}; got {first_hold!r}")
    index = FIRST_HOLDS.index(first_hold)
    return approach_scenario(holds=HOLDS[index:], legs=LEGS[index:], **changes)


def check_approach(scenario: ApproachScenario, kind: str, seed: int) -> None:
    """Build the filter and fly one step: a filter without a covariance, or a bad estimator
    field, raises ValueError before a campaign starts."""
    fly_approach(scenario, kind, runs=1, seed=seed, max_duration=scenario.dt)


def approach_chunk(scenario_name: str, scenario: ApproachScenario, kind: str, seed: int, first_run: int,
                   runs: int) -> dict:
    """Runs first_run .. first_run + runs - 1 of a cell (seeds seed + b): their flights (small
    dicts of figures; no trajectories). One Dask task."""
    flights = fly_approach(scenario, kind, runs=runs, seed=seed + first_run)
    return {'runs': runs, 'flights': flights}


def _flatten(prefix: str, value, row: dict) -> None:
    """summarize()'s nested figures as flat columns; a statistic that is None (no run gave
    it) becomes its four columns of None, so every row has the same columns."""
    if value is None:
        row.update({f'{prefix}_{name}': None for name in STATISTICS})
    elif isinstance(value, dict):
        for key, item in value.items():
            _flatten(f'{prefix}_{_column(key)}' if prefix else _column(key), item, row)
    else:
        row[prefix] = value


def combine_approach(partials: list[dict]) -> dict:
    """The readings of a cell from its batches, in batch order: summarize() of all its flights,
    flattened (see the module docstring), with contact_rate."""
    flights = [flight for partial in partials for flight in partial['flights']]
    summary = summarize(flights)
    row = {'contact_rate': summary['outcomes']['contact'] / summary['runs']}
    _flatten('', {key: value for key, value in summary.items() if key != 'runs'}, row)
    return row
