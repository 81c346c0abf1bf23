"""The server side's entry points: one module per console script (``fedhpg-run``:
:mod:`.launcher`, ``fedhpg-server``: :mod:`.server`, ``fedhpg-plan``, ``fedhpg-plot``,
``fedhpg-keys``, ``fedhpg-record``, ``fedhpg-cluster``: :mod:`.cluster`) and the Python API
(:mod:`.api`, which forks as ``fedhpg-run`` does). They build on the run-time code of
:mod:`fedhpg.server`, and nothing there imports them (a contract in ``pyproject.toml``).
"""
