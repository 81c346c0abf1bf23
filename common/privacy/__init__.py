"""Privacy maths: agent-level differential privacy and secure aggregation, as pure functions.

- :mod:`.dp`: each agent's update Δ_k = θ_k − θ̃ clipped to an L2 norm C, the Gaussian noise of
  the sum (central, or split across agents), adaptive clipping from a noisy quantile estimate;
- :mod:`.accounting`: the subsampled Gaussian mechanism's (ε, δ) over the rounds, from Google's
  ``dp-accounting`` (RDP or privacy-loss distributions), and σ calibrated to a target ε;
- :mod:`.fixedpoint`: real vectors as integers modulo 2⁶⁴, so masked sums are exact;
- :mod:`.shamir`: Shamir's t-of-n secret sharing over the prime field GF(2⁵²¹ − 1);
- :mod:`.masks`: X25519 key agreement, HKDF, the AES-CTR pseudorandom masks and the AES-GCM
  channel between two agents (the ``cryptography`` package);
- :mod:`.secagg`: the secure aggregation protocol (SecAgg, Bonawitz et al. 2017, with the
  SecAgg+ neighbour graph of Bell et al. 2020) as an agent's and a server's state, no wire.

Nothing here imports the wire or the process plumbing (import-linter checks): the pools and
the agent program carry these values in their messages.
"""
