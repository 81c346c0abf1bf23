"""The sections of a run's configuration, one module each, assembled by
:class:`fedhpg.common.configuration.config.RunConfig`.

Every process imports the configuration first, so these modules are pure Python (no torch,
zmq, gymnasium or hydra): that is why they sit together here rather than inside the packages
that read them (the engine, the privacy code and the algorithms import torch on import, and
``fedhpg.common`` may not import ``fedhpg.server``). Each module's docstring names its reader.
"""
