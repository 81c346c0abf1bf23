"""What makes one agent differ from another: its environment variant (:mod:`.variants`), its
budget and device fields drawn from a population or read from a trace (:mod:`.population`),
and the emulated device those fields describe (:mod:`.device`). Each is made per agent index,
never as a K-long list.
"""
