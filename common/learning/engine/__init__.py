"""The engine: many agents' local updates as rows of one batch, on a backend.

- :mod:`.engine`: a group's per-agent constants and memory plan; ``begin`` starts a round;
- :mod:`.round`: a round's rows and the primitives an algorithm's loop is written with
  (sample, coefficients, gradients, mean gradients, log-probabilities, bookkeeping);
- :mod:`.backend`: the protocol a backend implements (the compiled one is in
  ``common/learning/batched``);
- :mod:`.torch_backend`: torch on any device, every policy and family;
- :mod:`.estimate`: the run's estimator applied to a batch (the torch definition);
- :mod:`.sampling`: one episode in every copy of every row, stepped together;
- :mod:`.copies`: where the copies live (torch families on the device, gymnasium elsewhere);
- :mod:`.policy_rows`: the policy's own maths applied per row;
- :mod:`.trajectories`: the time-major batch of many rows' trajectories;
- :mod:`.memory`: what a round holds on the device, and its chunks;
- :mod:`.devices`: whether ``algo.device`` can be used here.
"""
