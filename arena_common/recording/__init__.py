"""Flight logs: MCAP recording, repair, replay and export (:mod:`.mcap`) and plots (:mod:`.plots`)."""
