"""The engine: many agents' local updates as rows of one batch, in torch on any device.

- :mod:`.engine`: the primitives an algorithm's loop is written with (sample, coefficients,
  gradients, log-probabilities, bookkeeping) and the rows of a round;
- :mod:`.sampling`: one episode in every copy of every row, stepped together;
- :mod:`.copies`: where the copies live (torch families on the device, gymnasium elsewhere);
- :mod:`.policy_rows`: the policy's own maths applied per row;
- :mod:`.trajectories`: the time-major batch of many rows' trajectories;
- :mod:`.devices`: whether ``algo.device`` can be used here.
"""
