"""The application layer: what the command line, the nodes, the fleet and the bench share, and
the only place below them that opens files.

The core (``model``, ``structure``, ``fdi``, ``tmcm``) takes arrays and records; this layer reads
recordings into them (:mod:`~youbot_fdi.app.recordings`, :mod:`~youbot_fdi.app.replay`), loads
the configuration a pipeline runs with (:mod:`~youbot_fdi.app.config`), and writes event logs and
report figures (:mod:`~youbot_fdi.app.eventlog`, :mod:`~youbot_fdi.app.report`).
"""
