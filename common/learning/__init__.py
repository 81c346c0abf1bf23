"""The learning side, pure maths and no plumbing: the algorithms (:mod:`.algorithms`), the
engine that runs many agents' local updates as rows of one batch (:mod:`.engine`, compiled in
:mod:`.batched`), the estimators and what they build on (:mod:`.estimators`,
:mod:`.staircase`, :mod:`.importance`, :mod:`.policies`, :mod:`.optim`,
:mod:`.randomness`), what a run's names resolve to on an agent's side (:mod:`.components`,
:mod:`.worker`, :mod:`.group`), the attacks and the Byzantine filter (:mod:`.attacks`,
:mod:`.byzantine_filter`) and Theorem 1's bound and planner (:mod:`.bounds`,
:mod:`.planning`). Nothing here imports the wire, the process plumbing, zmq or hydra.
"""
