"""The server side: its run-time code here (assembly, serving, the coordinator, buffered
rounds, :mod:`.strategies`, :mod:`.pools`, checkpoints, metrics) and its entry points, the
console scripts and the Python API, in :mod:`.commands`."""
