"""What the server and the agent share, one sub-package per role: a run's settings
(:mod:`.configuration`), agents' work as typed records (:mod:`.records`), what makes one agent
differ from another (:mod:`.heterogeneity`), the maths of learning (:mod:`.learning`), privacy
(:mod:`.privacy`), the wire (:mod:`.wire`) and the process plumbing (:mod:`.runtime`)."""
