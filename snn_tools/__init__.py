"""snn_tools: what runs around the pipeline, never inside a node. One subpackage per purpose:

* ``bags``: a recorded run read back, and its report;
* ``run``: the closed-loop demo over ROS 2 (separate processes or one), numba's cache at install;
* ``live``: the live view from outside (a Foxglove client, the layout, a snapshot);
* ``campaign``: Monte-Carlo campaigns on Dask (specs, cells, tables, the interactive page);
* ``experiments``: the paper's tables and ours (results/REPORT.md), sensors, spike budget, faults;
* ``neuromorphic``: NIR export, the Brian2 re-run, the chip network, the cost per estimate;
* ``bench``: speed (filter steps, the loop over ROS, latency, campaigns, live view, codecs).

``paths``, ``progress`` and ``figures`` serve them all. It may import the core (snn_estimator)
and the ROS layer (scenario_nodes); neither of those imports it, and a subpackage imports only
those listed before it.
"""
