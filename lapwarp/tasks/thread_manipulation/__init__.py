"""Thread Manipulation track: ThreadInHole (``thread_in_hole``), RopeThreading (``rope_threading``); LigatingLoop is
not implemented yet."""
