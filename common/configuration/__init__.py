"""A run's configuration: the typed config and its sections (:mod:`.settings`), the keys and
what each is for (:mod:`.run_keys`, :mod:`.run_roles`), the names that pick code
(:mod:`.registry`, :mod:`.vocabularies`), where agents run (:mod:`.placement`), whom a key
file speaks for (:mod:`.key_names`) and the one error a wrong setting raises
(:mod:`.config_error`).

Every process imports the configuration first, so everything here is pure Python: no torch,
zmq, gymnasium, hydra or environment (a contract in ``pyproject.toml``).
"""
