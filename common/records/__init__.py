"""Agents' work as typed records: what a round produces (:mod:`.types`), records held as
columns (:mod:`.columns`, :mod:`.round_columns`) and the bounds every message field carries
(:mod:`.limits`), which the codec enforces. Pure Python and numpy.
"""
