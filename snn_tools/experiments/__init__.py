"""The paper's experiments and ours: every table of results/REPORT.md, the sensor tables, the spike
budget, the fault matrix, the approach
from 5 km to contact."""
