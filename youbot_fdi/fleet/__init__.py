"""A fleet's recordings on a distributed engine (``youbot-fdi fleet``): one Dask task per recording
runs the same pipeline objects as ``replay`` and identifies friction on its fault-free stretch;
the results become a CSV, an HTML report and a friction trend test per wheel.

Layering: like ``nodes``, an adapter over the core (``fdi``, ``bag``); Dask is imported only when a
run starts (optional extra ``fleet``)."""
