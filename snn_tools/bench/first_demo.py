"""``python -m snn_tools.bench.first_demo``: how long a newcomer's first ``make demo`` takes.

Clones HEAD into a temporary folder (a fresh checkout, no .venv, no numba cache), runs
``make venv`` (the virtual environment and the kernels the demo needs) and then ``make demo``
there, times each as a whole process and writes the figures, with the machine's CPU count and
load, to ``--out``. The folder (~1.5 GB) is removed afterwards. pip's download cache
(~/.cache/pip) is the machine's: on a machine that never downloaded the wheels the first phase
also waits for the network.

Standard library only: it runs with the Python that creates the venv (``make time-first-demo``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def timed(command: list[str], cwd: Path, log: Path) -> float:
    """Wall seconds of ``command`` in ``cwd`` (output appended to ``log``); RuntimeError if it fails."""
    started = time.monotonic()
    with log.open('a') as handle:
        result = subprocess.run(command, cwd=cwd, stdout=handle, stderr=subprocess.STDOUT)
    if result.returncode != 0:
        raise RuntimeError(f'{" ".join(command)} failed ({result.returncode}): see {log}')
    return time.monotonic() - started


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog='first_demo', description=__doc__.split('\n\n')[0])
    parser.add_argument('--python', default='python3.11', help='the Python that creates .venv (make PYTHON=)')
    parser.add_argument('--out', type=Path, default=ROOT / 'results' / 'first_demo.json')
    parser.add_argument('--keep', action='store_true', help='keep the temporary checkout')
    args = parser.parse_args(argv)
    commit = subprocess.run(['git', 'rev-parse', '--short', 'HEAD'], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout.strip()
    folder = Path(tempfile.mkdtemp(prefix='snn_first_demo_'))
    checkout, log = folder / 'snn_rendezvous', folder / 'make.log'
    load_before = os.getloadavg()
    try:
        subprocess.run(['git', 'clone', '-q', str(ROOT), str(checkout)], check=True)
        venv = timed(['make', 'venv', f'PYTHON={args.python}'], checkout, log)
        demo = timed(['make', 'demo', f'PYTHON={args.python}'], checkout, log)
    except RuntimeError as error:
        print(error, file=sys.stderr)
        return 1
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
    figures = {'commit': commit, 'date': datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds'),
               'cpus': os.cpu_count(), 'load_average_before': [round(v, 2) for v in load_before],
               'load_average_after': [round(v, 2) for v in os.getloadavg()],
               'make_venv_s': round(venv, 1), 'make_demo_s': round(demo, 1), 'first_make_demo_s': round(venv + demo, 1),
               'goal_s': 180.0}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(figures, indent=2) + '\n')
    print(f'first make demo on a fresh clone of {commit}: {venv + demo:.0f} s (venv and the demo\'s kernels '
          f'{venv:.0f} s, the demo {demo:.0f} s) -> {args.out}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
