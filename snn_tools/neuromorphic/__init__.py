"""The networks on neuromorphic terms: NIR export, the Brian2 re-run, the chip network's results,
the cost per estimate."""
