"""basilisk_plant: the truth flown by Basilisk (two-body gravity, J2, thrust limits) instead of
the CW model the filters use: same topics, modes, /clock and control input as cw_plant.

Needs the basilisk extra (bsk==2.12.1). Nothing is downloaded: the J2 coefficient is set
directly and only Basilisk's core modules are imported; caches go to ``cache_dir``.
"""

from __future__ import annotations

from snn_estimator.plant.basilisk_truth import BasiliskPlant

from .core_objects import orbit_settings
from .parameter_tables import BASILISK_PLANT
from .plant_node import PlantNode
from .runtime import run_node


class BasiliskPlantNode(PlantNode):
    """Wraps :class:`snn_estimator.plant.basilisk_truth.BasiliskPlant` (a clipped thrust command is
    counted in ``saturated_steps`` and logged)."""

    NAME, SPECS = 'basilisk_plant', BASILISK_PLANT

    def make_plant(self, p: dict) -> BasiliskPlant:
        return BasiliskPlant(p['initial_state'], p['process_noise'], seeds=[p['seed']], dt=p['time_step'],
                             orbit=orbit_settings(p), chaser_mass=p['chaser_mass'],
                             thrust_limit=p['thrust_limit'], cache_dir=p['cache_dir'] or None)


def main(args=None) -> int:
    return run_node(BasiliskPlantNode, args, 'basilisk_plant')


if __name__ == '__main__':
    raise SystemExit(main())
